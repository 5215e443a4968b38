"""The one fleet.toml reader (edge and mock): good files parse, every bad input of section 12 is
one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from udan.firmware_mock import fleet as mock_fleet
from udan.fleetfile import CarEntry, FleetFileError, load_fleet

KEY1 = bytes(range(32)).hex()
KEY2 = bytes(range(100, 132)).hex()

GOOD = f"""
[[car]]
id = 1
marker = 11
port = 9101
key = "{KEY1}"
start = [2, 3]
serial = "/dev/ttyUSB0"
[car.faults]
loss = 0.1

[[car]]
id = 2
marker = 12
address = "10.0.0.22:9100"
key_file = "keys/car2.key"

[[car]]
id = 3
marker = 13
key = "{KEY2.upper()}"
marker_height_m = 0.12
"""


def _write(tmp_path: Path, text: str | bytes) -> Path:
    path = tmp_path / "fleet.toml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def keys_dir(tmp_path: Path) -> Path:
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "car2.key").write_bytes(bytes(range(50, 82)))
    (tmp_path / "keys" / "hex.key").write_text(KEY2 + "\n")
    return tmp_path


def test_good_file_parses_and_the_mock_reads_it_too(keys_dir: Path) -> None:
    path = _write(keys_dir, GOOD)
    cars = load_fleet(path)
    assert cars == [
        CarEntry(1, 11, bytes(range(32)), "127.0.0.1", 9101, "/dev/ttyUSB0"),
        CarEntry(2, 12, bytes(range(50, 82)), "10.0.0.22", 9100),
        CarEntry(3, 13, bytes(range(100, 132)), marker_height_m=0.12),
    ]
    assert [c.address for c in cars] == [("127.0.0.1", 9101), ("10.0.0.22", 9100), None]
    assert "key=" not in repr(cars[0])  # a key never shows in a log line
    specs = mock_fleet.load_fleet(path, base_port=9200)
    assert [(s.car_id, s.marker, s.key, s.port) for s in specs] == [
        (c.car_id, c.marker, c.key, s.port) for c, s in zip(cars, specs, strict=True)
    ]
    assert specs[0].start == (2, 3) and specs[0].faults == {"loss": 0.1}


def test_hex_key_file_and_port_zero(keys_dir: Path) -> None:
    text = '[[car]]\nid = 7\nmarker = 0\nport = 0\nkey_file = "keys/hex.key"\n'
    (car,) = load_fleet(_write(keys_dir, text))
    assert car.key == bytes(range(100, 132))
    assert car.address is None  # port 0: "any free port" on the mock, learned from the JOIN


def _car(**fields: object) -> str:
    body = {"id": 1, "marker": 1, "key": f'"{KEY1}"', **fields}
    return "[[car]]\n" + "".join(f"{k} = {v}\n" for k, v in body.items() if v is not None)


BAD = {
    "not toml": ("[[car]\nid = 1", "malformed TOML"),
    "no cars": ("title = 'x'\n", "no [[car]] tables"),
    "empty car list": ("car = []\n", "no [[car]] tables"),
    "car not a table": ("car = [1]\n", "car #1: must be a table"),
    "unknown field": (_car(colour='"red"'), "car #1: unknown field(s) colour"),
    "missing id": (_car(id=None), "car #1: missing id"),
    "missing marker": (_car(marker=None), "car #1: missing marker"),
    "missing key": (_car(key=None), "car 1: give exactly one of key or key_file"),
    "key and key_file": (_car(key_file='"k"'), "car 1: give exactly one of key or key_file"),
    "key not hex": (_car(key='"zz' + "0" * 62 + '"'), "car 1: key is not hex"),
    "key odd length": (_car(key='"abc"'), "car 1: key is not hex"),
    "key too short": (_car(key='"' + "00" * 31 + '"'), "must be 32 bytes"),
    "key not a string": (_car(key="5"), "car 1: key must be a hex string"),
    "key_file missing": (_car(key=None, key_file='"nope.key"'), "cannot read key_file"),
    "id zero": (_car(id=0), "car #1: id must be an integer in 1-65534"),
    "id too big": (_car(id=65535), "car #1: id must be an integer in 1-65534"),
    "id bool": (_car(id="true"), "car #1: id must be an integer"),
    "marker range": (_car(marker=70000), "car 1: marker must be an integer in 0-65535"),
    "port and address": (_car(port=1, address='"h:2"'), "car 1: give port or address, not both"),
    "bad address": (_car(address='"nohost"'), "car 1: address must be HOST:PORT"),
    "port range": (_car(port=70000), "car 1: port must be an integer in 0-65535"),
    "serial empty": (_car(serial='""'), "car 1: serial must be a device path"),
    "height negative": (_car(marker_height_m=-0.1), "car 1: marker_height_m must be metres"),
    "height a camera's": (_car(marker_height_m=2.5), "car 1: marker_height_m must be metres"),
    "height text": (_car(marker_height_m='"10cm"'), "car 1: marker_height_m must be metres"),
    "duplicate id": (_car() + _car(marker=2), "duplicate car id 1"),
    "duplicate marker": (_car() + _car(id=2), "duplicate marker 1"),
    "duplicate port": (_car(port=9000) + _car(id=2, marker=2, port=9000), "duplicate port 9000"),
    "duplicate serial": (
        _car(serial='"/dev/a"') + _car(id=2, marker=2, serial='"/dev/a"'),
        "duplicate serial device /dev/a",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_line_naming_the_file(tmp_path: Path, case: str) -> None:
    text, expected = BAD[case]
    path = _write(tmp_path, text)
    with pytest.raises(FleetFileError) as err:
        load_fleet(path)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"fleet file {path}")
    assert expected in message


def test_unreadable_and_not_utf8(tmp_path: Path) -> None:
    with pytest.raises(FleetFileError, match=r"cannot read fleet file .*missing\.toml"):
        load_fleet(tmp_path / "missing.toml")
    path = _write(tmp_path, b"\xff\xfe[[car]]")
    with pytest.raises(FleetFileError, match="is not UTF-8 text"):
        load_fleet(path)


def test_mock_only_fields_are_ignored_by_the_edge(tmp_path: Path) -> None:
    # a fault value the mock refuses does not stop the edge from driving real cars
    path = _write(tmp_path, _car(start='"anywhere"') + "[car.faults]\nloss = 7\n")
    assert load_fleet(path)[0].car_id == 1
    with pytest.raises(FleetFileError):
        mock_fleet.load_fleet(path, base_port=0)


def test_the_mock_gives_a_car_without_a_port_one_from_base_port_or_refuses(tmp_path: Path) -> None:
    path = _write(tmp_path, _car() + _car(id=2, marker=2, port=9102))
    assert [s.port for s in mock_fleet.load_fleet(path, base_port=9100)] == [9101, 9102]
    with pytest.raises(FleetFileError, match=r"^fleet file .*: car 1: no port or address"):
        mock_fleet.load_fleet(path)
    with pytest.raises(FleetFileError, match=r"duplicate port 9102 on 127\.0\.0\.1"):
        mock_fleet.load_fleet(path, base_port=9101)
