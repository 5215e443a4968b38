"""Output folders: every command creates the folders it writes into, and says in one line when
it cannot (a file in the way, no permission)."""

from __future__ import annotations

from pathlib import Path


class FolderError(ValueError):
    """An output folder that does not exist and cannot be created."""


def ensure_folder(folder: str | Path, what: str) -> Path:
    """``folder`` created with its parents if missing; :class:`FolderError` naming ``what``
    (the flag) when that is impossible."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise FolderError(f"{what}: cannot create folder {folder} ({err.strerror})") from None
    return folder
