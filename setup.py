"""Everything about the package is in pyproject.toml but its C extension, which setuptools reads
from here (its pyproject table for extensions is still experimental): ``udan._kernels``, the
grid rules', grouping's and observation's loops (udan/_kernels.c), built by every install."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("udan._kernels", sources=["udan/_kernels.c"])])
