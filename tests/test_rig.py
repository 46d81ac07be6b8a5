"""The rig and the rig file: round trips, every malformed case, derived transforms."""

from __future__ import annotations

import copy
import dataclasses
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from app.sources.sim.head import default_rig
from app.storage.rigfile import load_rig, save_rig
from calib.camera import Intrinsics
from calib.errors import RigError
from calib.radiometry import Radiometry
from calib.rig import Eye, Rig, Sensor, rig_from_dict, rig_from_yaml, rig_to_dict, rig_to_yaml
from calib.transforms import invert, make_T

BASE = rig_to_dict(default_rig())


# -- round trips -------------------------------------------------------------------------------


def test_yaml_round_trip_is_exact() -> None:
    rig = default_rig()
    text = rig_to_yaml(rig)
    again = rig_from_yaml(text)
    assert again == rig
    assert rig_to_yaml(again) == text
    assert rig_to_dict(again) == BASE


def test_round_trip_keeps_optional_blocks() -> None:
    d = copy.deepcopy(BASE)
    nodes = [[0.001 * (r - c) for c in range(23)] for r in range(19)]
    block = {
        "model": "trifuse-range/1",
        "distance": {"start_m": 0.5, "step_m": 0.25, "coeffs_m": [0.03, 0.02, 0.01, 0.02, 0.03]},
        "offset": {"step_px": 8, "nodes_m": nodes},
        "amplitude": {"ref": 1500.0, "log_range": [-1.0, 1.0], "coeffs_m": [0.004, -0.001]},
    }
    d["sensors"]["tof"]["range_correction"] = block
    d["sensors"]["thermal_left"]["radiometry"] = {"gain": 1.02, "offset_k": -0.3}
    d["sensors"]["ccd_left"]["uncertainty"] = {"fx": 0.4, "T_rig_sensor": {"t_m": [1e-4] * 3}}
    rig = rig_from_dict(d)
    assert rig["tof"].range_correction.to_dict() == block
    assert rig_from_yaml(rig_to_yaml(rig)) == rig
    assert rig != default_rig()


def test_file_round_trip(tmp_path: Path) -> None:
    first = tmp_path / "first" / "rig.yaml"
    second = tmp_path / "second.yaml"
    assert save_rig(first, default_rig()) == first
    loaded = load_rig(first)
    assert loaded == default_rig()
    save_rig(second, loaded)
    assert load_rig(second) == loaded
    assert second.read_text(encoding="utf-8") == first.read_text(encoding="utf-8")


def test_save_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text("precious", encoding="utf-8")
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        save_rig(path, default_rig())
    assert path.read_text(encoding="utf-8") == "precious"
    save_rig(path, default_rig(), overwrite=True)
    assert load_rig(path) == default_rig()
    assert [p.name for p in tmp_path.iterdir()] == ["rig.yaml"]  # no temporary left behind


def test_load_errors_start_with_the_path(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    bad = copy.deepcopy(BASE)
    bad["sensors"]["ccd_left"]["intrinsics"]["fx"] = -1.0
    path.write_text(yaml.safe_dump(bad), encoding="utf-8")
    with pytest.raises(RigError, match=rf"^{path}: sensor 'ccd_left': field 'intrinsics\.fx'"):
        load_rig(path)
    with pytest.raises(RigError, match=rf"^{tmp_path / 'missing.yaml'}: cannot read rig file"):
        load_rig(tmp_path / "missing.yaml")


# -- malformed rig files -----------------------------------------------------------------------


def _set(*path: Any, value: Any) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        for key in path[:-1]:
            d = d[key]
        d[path[-1]] = value

    return mutate


def _del(*path: Any) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        for key in path[:-1]:
            d = d[key]
        del d[path[-1]]

    return mutate


def _pose(sensor: str, change: Callable[[np.ndarray], None]) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        T = np.array(d["sensors"][sensor]["T_rig_sensor"])
        change(T)
        d["sensors"][sensor]["T_rig_sensor"] = T.tolist()

    return mutate


def _scale(T: np.ndarray) -> None:
    T[:3, :3] *= 1.05


def _shear(T: np.ndarray) -> None:
    T[0, 1] += 0.1


def _reflect(T: np.ndarray) -> None:
    T[:3, 2] *= -1.0


def _last_row(T: np.ndarray) -> None:
    T[3] = [0.0, 0.0, 0.0, 2.0]


def _stringify(d: dict) -> None:
    T = d["sensors"]["ccd_left"]["T_rig_sensor"]
    d["sensors"]["ccd_left"]["T_rig_sensor"] = [[str(x) for x in row] for row in T]


S = r"sensor '{}': "
F = r"sensor '{}': field '{}': "
NOT_RIGID = r"sensor '{}': field 'T_rig_sensor': not a rigid transform: "


def case(id_: str, mutate: Callable[[dict], None], match: str, *marks: Any) -> Any:
    return pytest.param(mutate, match, id=id_, marks=marks)


MALFORMED = [
    # missing keys
    *(
        case(
            f"missing-{key}",
            _del("sensors", "ccd_left", key),
            S.format("ccd_left") + rf"missing key\(s\) \['{key}'\]",
        )
        for key in ("modality", "image_size", "intrinsics", "distortion", "T_rig_sensor")
    ),
    *(
        case(f"missing-top-{key}", _del(key), rf"^rig file: missing key\(s\) \['{key}'\]")
        for key in ("format", "reference", "sensors")
    ),
    case(
        "missing-intrinsics-cy",
        _del("sensors", "thermal_left", "intrinsics", "cy"),
        F.format("thermal_left", "intrinsics") + r"missing key\(s\) \['cy'\]",
    ),
    case(
        "missing-eye-role",
        _del("eyes", "left", "thermal"),
        r"field 'eyes\.left': missing key\(s\) \['thermal'\]",
    ),
    # wrong shapes
    case(
        "T-3x4",
        _set("sensors", "ccd_right", "T_rig_sensor", value=np.eye(4)[:3].tolist()),
        F.format("ccd_right", "T_rig_sensor") + "expected a 4x4 list of numbers",
    ),
    case(
        "T-ragged",
        _set("sensors", "ccd_right", "T_rig_sensor", value=[[1, 0], [0, 1, 0]]),
        F.format("ccd_right", "T_rig_sensor") + "expected a 4x4 list of numbers",
    ),
    case(
        "image_size-3",
        _set("sensors", "tof", "image_size", value=[176, 144, 3]),
        F.format("tof", "image_size") + r"expected \[width, height\] as two positive integers",
    ),
    case(
        "image_size-zero",
        _set("sensors", "tof", "image_size", value=[176, 0]),
        F.format("tof", "image_size") + "expected",
    ),
    case(
        "image_size-huge",  # allocating for it would take gigabytes before any check
        _set("sensors", "ccd_left", "image_size", value=[20000, 20000]),
        F.format("ccd_left", "image_size") + "20000x20000 is 400 megapixels; expected at most 50",
    ),
    case(
        "image_size-float",
        _set("sensors", "tof", "image_size", value=[176.0, 144]),
        F.format("tof", "image_size") + "expected",
    ),
    case(
        "distortion-3",
        _set("sensors", "thermal_right", "distortion", value=[0.1, 0.0, 0.0]),
        F.format("thermal_right", "distortion")
        + r"expected a list of 4, 5 or 8 numbers .*got \[0\.1",
    ),
    case(
        "distortion-not-list",
        _set("sensors", "thermal_right", "distortion", value=0.1),
        F.format("thermal_right", "distortion") + "expected a list of 4, 5 or 8 numbers",
    ),
    # non-rigid poses
    case(
        "T-scaled",
        _pose("ccd_left", _scale),
        NOT_RIGID.format("ccd_left") + "rotation block is not orthonormal",
    ),
    case(
        "T-shear",
        _pose("ccd_left", _shear),
        NOT_RIGID.format("ccd_left") + "rotation block is not orthonormal",
    ),
    case(
        "T-reflection",
        _pose("thermal_left", _reflect),
        NOT_RIGID.format("thermal_left") + r"rotation block is a reflection \(det = -1",
    ),
    case(
        "T-last-row",
        _pose("ccd_right", _last_row),
        NOT_RIGID.format("ccd_right") + r"last row must be \[0, 0, 0, 1\]",
    ),
    case(
        "T-nan",
        _set("sensors", "ccd_right", "T_rig_sensor", 0, 3, value=float("nan")),
        F.format("ccd_right", "T_rig_sensor") + "expected a finite number, got nan",
    ),
    # unknown keys
    case("unknown-top", _set("serial", value="A123"), r"^rig file: unknown key\(s\) \['serial'\]"),
    case(
        "unknown-sensor-key",
        _set("sensors", "tof", "serial", value="A123"),
        S.format("tof") + r"unknown key\(s\) \['serial'\]",
    ),
    case(
        "unknown-intrinsics-key",
        _set("sensors", "ccd_left", "intrinsics", "skew", value=0.0),
        F.format("ccd_left", "intrinsics") + r"unknown key\(s\) \['skew'\]",
    ),
    case(
        "unknown-eye-key",
        _set("eyes", "left", "tof", value="tof"),
        r"field 'eyes\.left': unknown key\(s\) \['tof'\]",
    ),
    # focal lengths
    case(
        "fx-negative",
        _set("sensors", "ccd_left", "intrinsics", "fx", value=-1333.0),
        F.format("ccd_left", "intrinsics.fx") + "focal length must be positive, got -1333.0",
    ),
    case(
        "fy-zero",
        _set("sensors", "thermal_right", "intrinsics", "fy", value=0),
        F.format("thermal_right", "intrinsics.fy") + "focal length must be positive, got 0.0",
    ),
    case(
        "fx-nan",
        _set("sensors", "tof", "intrinsics", "fx", value=float("nan")),
        F.format("tof", "intrinsics.fx") + "expected a finite number",
    ),
    # non-numeric values
    case(
        "fx-string",
        _set("sensors", "tof", "intrinsics", "fx", value="165.5"),
        F.format("tof", "intrinsics.fx") + "expected a number, got '165.5'",
    ),
    case(
        "cx-null",
        _set("sensors", "tof", "intrinsics", "cx", value=None),
        F.format("tof", "intrinsics.cx") + "expected a number, got None",
    ),
    case(
        "cy-bool",
        _set("sensors", "tof", "intrinsics", "cy", value=True),
        F.format("tof", "intrinsics.cy") + "expected a number, got True",
    ),
    case(
        "distortion-string",
        _set("sensors", "ccd_right", "distortion", 1, value="x"),
        F.format("ccd_right", "distortion") + "expected a number, got 'x'",
    ),
    case(
        "T-word",
        _set("sensors", "ccd_left", "T_rig_sensor", 1, 1, value="one"),
        F.format("ccd_left", "T_rig_sensor") + "expected a number, got 'one'",
    ),
    case(
        "T-numeric-strings",
        _stringify,
        F.format("ccd_left", "T_rig_sensor") + "expected a number, got '0.99980",
    ),
    case(
        "image_size-strings",
        _set("sensors", "tof", "image_size", value=["176", "144"]),
        F.format("tof", "image_size") + "expected",
    ),
    case(
        "modality-unknown",
        _set("sensors", "tof", "modality", value="lidar"),
        F.format("tof", "modality") + r"expected one of \['color', 'thermal', 'tof'\], got "
        "'lidar'",
    ),
    # structure
    case(
        "sensor-not-mapping",
        _set("sensors", "ccd_left", value=[1, 2]),
        S.format("ccd_left") + "expected a mapping, got list",
    ),
    case("sensors-empty", _set("sensors", value={}), "field 'sensors': the rig has no sensors"),
    case(
        "optional-not-mapping",
        _set("sensors", "tof", "range_correction", value=5),
        F.format("tof", "range_correction") + "expected a mapping, got int",
    ),
    case("eyes-list", _set("eyes", value=[]), "field 'eyes': expected a mapping"),
    # reference
    case(
        "reference-unknown",
        _set("reference", value="lidar"),
        r"^field 'reference': sensor 'lidar' is not in the rig",
    ),
    case(
        "reference-list",
        _set("reference", value=["tof"]),
        "field 'reference': expected a sensor name",
    ),
    case(
        "reference-not-identity",
        _set("reference", value="ccd_left"),
        F.format("ccd_left", "T_rig_sensor")
        + "the reference sensor defines the rig frame, so its pose must be the identity",
    ),
    # eyes
    case(
        "eye-unknown-sensor",
        _set("eyes", "left", "color", value="ccd_middle"),
        r"eyes\.left\.color: unknown sensor 'ccd_middle'",
    ),
    case(
        "eye-wrong-modality",
        _set("eyes", "right", "thermal", value="ccd_right"),
        r"eyes\.right\.thermal: sensor 'ccd_right' has modality 'color', expected 'thermal'",
    ),
    case(
        "eye-tof-as-color",
        _set("eyes", "left", "color", value="tof"),
        r"eyes\.left\.color: sensor 'tof' has modality 'tof', expected 'color'",
    ),
    # format
    case(
        "format-wrong",
        _set("format", value="trifuse-rig/2"),
        r"^field 'format': expected 'trifuse-rig/1', got 'trifuse-rig/2'",
    ),
    case("format-number", _set("format", value=1), r"^field 'format': expected 'trifuse-rig/1'"),
]


@pytest.mark.parametrize(("mutate", "match"), MALFORMED)
def test_malformed_dict_raises_rig_error(mutate: Callable[[dict], None], match: str) -> None:
    d = copy.deepcopy(BASE)
    mutate(d)
    with pytest.raises(RigError, match=match):
        rig_from_dict(d)


@pytest.mark.parametrize(("mutate", "match"), MALFORMED)
def test_malformed_text_raises_rig_error(mutate: Callable[[dict], None], match: str) -> None:
    d = copy.deepcopy(BASE)
    mutate(d)
    with pytest.raises(RigError, match=match):
        rig_from_yaml(yaml.safe_dump(d, sort_keys=False))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("format: [trifuse-rig/1\nreference: tof\n", "rig file is not valid YAML"),
        ("format: trifuse-rig/1\n\treference: tof\n", "rig file is not valid YAML"),
        ("sensors: {a: 1}\nsensors: {b: 2}\n  - x\n", "rig file is not valid YAML"),
        ("", "rig file: expected a mapping, got NoneType"),
        ("- format\n- sensors\n", "rig file: expected a mapping, got list"),
    ],
    ids=["unclosed", "tab", "bad-indent", "empty", "list"],
)
def test_invalid_yaml_text(text: str, match: str) -> None:
    with pytest.raises(RigError, match=match):
        rig_from_yaml(text)


def test_rig_constructor_validates() -> None:
    rig = default_rig()
    with pytest.raises(RigError, match="reference: sensor 'lidar' is not in the rig"):
        Rig(sensors=rig.sensors, reference="lidar")
    with pytest.raises(RigError, match=r"eyes\.x\.thermal: sensor 'tof' has modality 'tof'"):
        Rig(sensors=rig.sensors, reference="tof", eyes={"x": Eye("ccd_left", "tof")})


def test_with_sensor_replaces_one_sensor_in_a_copy() -> None:
    rig = default_rig()
    thermal = rig["thermal_left"]
    trimmed = dataclasses.replace(thermal, radiometry=Radiometry(manual_offset_k=1.5))
    new = rig.with_sensor(trimmed)
    assert new["thermal_left"] is trimmed and rig["thermal_left"] is thermal
    assert new.names == rig.names and new.reference == rig.reference and new.eyes == rig.eyes
    assert all(new[n] is rig[n] for n in rig.names if n != "thermal_left")
    assert rig_from_yaml(rig_to_yaml(new)) == new
    with pytest.raises(KeyError, match="no sensor 'lidar' in the rig"):
        rig.with_sensor(dataclasses.replace(thermal, name="lidar"))
    with pytest.raises(RigError, match=r"eyes\.left\.thermal: sensor 'thermal_left' has modality"):
        rig.with_sensor(dataclasses.replace(thermal, modality="color"))


# -- derived transforms ------------------------------------------------------------------------

# Entries of T are O(1) (rotations) and O(0.1 m) (baselines): a few ulp is below 1e-15.
T_TOL = 1e-15


def test_T_of_a_sensor_to_itself_is_identity() -> None:
    rig = default_rig()
    for name in rig.names:
        np.testing.assert_allclose(rig.T(name, name), np.eye(4), rtol=0, atol=T_TOL)


def test_T_composes_and_inverts() -> None:
    rig = default_rig()
    for a, b, c in itertools.product(rig.names, repeat=3):
        np.testing.assert_allclose(rig.T(a, b) @ rig.T(b, c), rig.T(a, c), rtol=0, atol=T_TOL)
    for a, b in itertools.product(rig.names, repeat=2):
        np.testing.assert_allclose(rig.T(a, b), invert(rig.T(b, a)), rtol=0, atol=T_TOL)


def test_T_from_the_reference_is_the_inverse_pose() -> None:
    rig = default_rig()
    np.testing.assert_array_equal(rig["tof"].T_rig_sensor, np.eye(4))
    for name in rig.names:
        T_sensor_tof = invert(rig[name].T_rig_sensor)
        np.testing.assert_allclose(rig.T(name, "tof"), T_sensor_tof, rtol=0, atol=T_TOL)
        np.testing.assert_allclose(rig.T("tof", name), rig[name].T_rig_sensor, rtol=0, atol=T_TOL)


def test_T_of_a_toy_rig_by_hand() -> None:
    cam = Intrinsics(100.0, 100.0, 50.0, 50.0)
    sensors = {
        "tof": Sensor("tof", "tof", (101, 101), cam, np.eye(4)),
        "cam": Sensor("cam", "color", (101, 101), cam, make_T(np.eye(3), [0.1, 0.0, 0.0])),
    }
    rig = Rig(sensors=sensors, reference="tof")
    # The camera sits 10 cm right of the TOF, so a TOF-frame point appears 10 cm further
    # left (x smaller) in the camera's frame.
    np.testing.assert_array_equal(rig.T("cam", "tof"), make_T(np.eye(3), [-0.1, 0.0, 0.0]))


@pytest.mark.parametrize(("dst", "src"), [("lidar", "tof"), ("tof", "lidar")])
def test_T_of_an_unknown_sensor_is_a_key_error(dst: str, src: str) -> None:
    rig = default_rig()
    with pytest.raises(KeyError, match="no sensor 'lidar' in the rig"):
        rig.T(dst, src)


def test_lookup_helpers() -> None:
    rig = default_rig()
    assert rig.names == ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
    assert rig.by_modality("thermal") == ["thermal_left", "thermal_right"]
    assert "tof" in rig
    assert "lidar" not in rig
    assert (rig["tof"].width, rig["tof"].height) == (176, 144)


def test_modality_of_a_sensor_name() -> None:
    from calib.rig import modality_of_name

    assert modality_of_name("CCD_left") == "color" and modality_of_name("rgb") == "color"
    assert modality_of_name("LWIR_2") == "thermal" and modality_of_name("depth0") == "tof"
    assert modality_of_name("imu") is None and modality_of_name("") is None
