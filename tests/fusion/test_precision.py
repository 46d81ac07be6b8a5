"""fusion.precision (the method's section 4.1 / Table 1) and ``trifuse analyze``."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import run_cli
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.rigfile import save_rig
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig, Sensor, rig_to_yaml
from trifuse.calib.tof import region_map
from trifuse.calib.transforms import make_T
from trifuse.fusion.precision import (
    analyze_precision,
    default_tof_pixels,
    distance_error_shifts,
    pixel_key,
    sample_distances,
    threshold_distance,
    tof_pixel_error_shifts,
    tof_pixel_label,
)

# -- a hand-built rig with a closed form ----------------------------------------------------

F = 1333.0  # focal length of the sensor, px
F_TOF = 165.5  # focal length of the TOF, px
B = 0.06  # sideways baseline, m: the sensor sits at x = +B in the TOF frame
TOF_PP = (87.5, 71.5)


def sideways_rig(baseline_m: float = B, f: float = F) -> Rig:
    """A TOF at the origin and a camera ``cam`` at (baseline_m, 0, 0), identity rotation, no
    distortion anywhere: the camera's pixel of a TOF-frame point P is
    ``u = cx + f (X - b) / Z``, ``v = cy + f Y / Z``."""
    tof = Sensor("tof", "tof", (176, 144), Intrinsics(F_TOF, F_TOF, *TOF_PP), np.eye(4))
    cam = Sensor(
        "cam",
        "color",
        (1280, 960),
        Intrinsics(f, f, 639.5, 479.5),
        make_T(np.eye(3), [baseline_m, 0.0, 0.0]),
    )
    return Rig(sensors={"tof": tof, "cam": cam}, reference="tof")


def closed_form_threshold(f: float, b: float, dd: float, t: float) -> float:
    """Root of f b dd / (d (d + dd)) = t, i.e. d^2 + dd d - f b dd / t = 0, d > 0."""
    return (-dd + np.sqrt(dd * dd + 4.0 * f * b * dd / t)) / 2.0


@pytest.mark.parametrize("dd", [0.041, 0.015])
def test_distance_error_closed_form(dd: float) -> None:
    """On the optical axis P = (0, 0, d), so u(d) = cx - f b / d and
    dx(d) = u(d + dd) - u(d) = f b / d - f b / (d + dd) = f b dd / (d (d + dd)) > 0."""
    rig = sideways_rig()
    d = sample_distances()
    shift = distance_error_shifts(rig, TOF_PP, d, dd)["cam"]
    expected = F * B * dd / (d * (d + dd))
    np.testing.assert_allclose(shift[:, 0], expected, rtol=1e-12, atol=1e-12)
    assert np.all(shift[:, 1] == 0.0)

    a = analyze_precision(rig, distance_error_m=dd, threshold_px=0.5)
    r = a.distance_error[pixel_key(TOF_PP)]["cam"]
    d_star = closed_form_threshold(F, B, dd, 0.5)
    assert 0.1 < d_star < 10.0
    assert r.x_m == pytest.approx(d_star, rel=0.01)  # the criterion
    assert abs(r.x_m - d_star) < 1e-6  # bisection to 1e-7 m
    assert r.y_m is None
    np.testing.assert_allclose(r.dx_px, expected, rtol=1e-12, atol=1e-12)


def test_distance_error_sign_follows_the_baseline() -> None:
    """A camera on the other side (b < 0) sees the shift with the opposite sign."""
    d = sample_distances()
    left = distance_error_shifts(sideways_rig(-B), TOF_PP, d, 0.041)["cam"]
    right = distance_error_shifts(sideways_rig(B), TOF_PP, d, 0.041)["cam"]
    np.testing.assert_allclose(left, -right, rtol=1e-12, atol=1e-12)
    assert np.all(left[:, 0] < 0)


def test_tof_pixel_error_closed_form() -> None:
    """TOF pixel (cx + δ, cy): normalised x = δ / f_tof, ray (x, 0, 1) / s with
    s = sqrt(1 + x^2), P = d (x, 0, 1) / s, so u = cx + f (x - b s / d) and
    dx(d) = f x - f b (s - 1) / d, dy = 0. Above 0.5 px over the whole range: x_m = 10."""
    rig = sideways_rig()
    delta = 0.5
    d = sample_distances()
    x = delta / F_TOF
    s = np.sqrt(1.0 + x * x)
    expected = F * x - F * B * (s - 1.0) / d
    shift = tof_pixel_error_shifts(rig, TOF_PP, d, delta)["cam"]
    np.testing.assert_allclose(shift[:, 0], expected, rtol=1e-9, atol=1e-9)
    assert np.all(shift[:, 1] == 0.0)
    a = analyze_precision(rig, tof_pixel_error_px=delta)
    r = a.tof_pixel_error[pixel_key(TOF_PP)]["cam"]
    assert r.x_m == 10.0  # the shift (about 4 px) exceeds 0.5 px over the whole range
    assert r.y_m is None


def test_tof_pixel_error_closed_form_threshold() -> None:
    """With the camera on the left (b < 0) the pixel-error shift falls with distance,
    dx(d) = f x + C / d with C = f |b| (s - 1); for a threshold t = f x + C / 2 it crosses at
    d = C / (t - f x) = 2 m."""
    f, delta = 1000.0, 10.0
    rig = sideways_rig(-B, f)
    x = delta / F_TOF
    c = f * B * (np.sqrt(1.0 + x * x) - 1.0)
    t = f * x + c / 2.0
    a = analyze_precision(rig, tof_pixel_error_px=delta, threshold_px=t)
    r = a.tof_pixel_error[pixel_key(TOF_PP)]["cam"]
    assert r.x_m == pytest.approx(2.0, abs=1e-6)
    assert r.y_m is None


def test_shifts_are_zero_for_zero_errors() -> None:
    a = analyze_precision(default_rig(), distance_error_m=0.0, tof_pixel_error_px=0.0)
    for kind in ("distance_error", "tof_pixel_error"):
        for per_sensor in a.results(kind).values():
            for r in per_sensor.values():
                assert np.all(r.dx_px == 0.0) and np.all(r.dy_px == 0.0)
                assert r.x_m is None and r.y_m is None


# -- threshold_distance --------------------------------------------------------------------


def test_threshold_distance_interpolates_and_bisects() -> None:
    d = sample_distances(step_m=0.5)
    assert d[0] == 0.1 and d[-1] == 10.0

    def exact(x: np.ndarray) -> np.ndarray:
        return -3.0 / np.asarray(x)  # |shift| = 3 / d crosses 0.5 at d = 6 m

    assert threshold_distance(d, exact(d), 0.5, exact) == pytest.approx(6.0, abs=1e-6)
    linear = threshold_distance(d, exact(d), 0.5)  # linear in |shift| between samples
    assert linear == pytest.approx(6.0, abs=0.05)
    assert threshold_distance(d, np.full(d.shape, 0.49), 0.5) is None
    assert threshold_distance(d, np.full(d.shape, 0.5), 0.5) == 10.0
    assert threshold_distance(d, np.full(d.shape, np.nan), 0.5) is None
    # not monotonic: the largest distance at or above the threshold wins
    bumpy = np.where((d > 3) & (d < 5), 1.0, 0.0)
    assert 4.6 <= threshold_distance(d, bumpy, 0.5) <= 5.1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"threshold_px": 0.0}, "threshold_px"),
        ({"threshold_px": -1.0}, "threshold_px"),
        ({"shift_px": [1.0, 2.0]}, "shape"),
        ({"distance_m": [2.0, 1.0, 3.0]}, "ascending"),
    ],
)
def test_threshold_distance_rejects_bad_input(kwargs: dict, match: str) -> None:
    args = {"distance_m": [1.0, 2.0, 3.0], "shift_px": [3.0, 2.0, 1.0], "threshold_px": 0.5}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        threshold_distance(**args)


def test_sample_distances() -> None:
    d = sample_distances()
    assert d.size == 991
    assert d[0] == 0.1 and d[-1] == 10.0 and d[20] == 0.3
    np.testing.assert_allclose(np.diff(d), 0.01, atol=1e-9)
    d = sample_distances(0.1, 1.0, 0.4)  # 0.1, 0.5, 0.9 and the end
    np.testing.assert_allclose(d, [0.1, 0.5, 0.9, 1.0])
    for bad in ({"step_m": 0.0}, {"step_m": -0.1}, {"min_m": 2.0, "max_m": 1.0}):
        with pytest.raises(ValueError):
            sample_distances(**bad)
    with pytest.raises(ValueError, match="at most"):
        sample_distances(step_m=1e-9)


# -- the default head ----------------------------------------------------------------------

RIG = default_rig()
CCD = ("ccd_left", "ccd_right")
THERMAL = ("thermal_left", "thermal_right")


@pytest.fixture(scope="module")
def head_41():
    return analyze_precision(RIG, distance_error_m=0.041)


@pytest.fixture(scope="module")
def head_15():
    return analyze_precision(RIG, distance_error_m=0.015)


def test_default_tof_pixels_are_the_principal_point_and_region_3_edge() -> None:
    tof = RIG["tof"]
    (u0, v0), (u3, v3) = default_tof_pixels(RIG)
    assert (u0, v0) == (tof.intrinsics.cx, tof.intrinsics.cy)
    assert v3 == tof.intrinsics.cy  # on the TOF's x axis
    regions = region_map(tof.width, tof.height)
    row = round(v3)
    assert regions[row, int(u3)] == 3 and regions[row, int(u3) + 1] == 4
    assert tof_pixel_label(RIG, (u0, v0)) == "principal point"
    assert tof_pixel_label(RIG, (u3, v3)) == "region 3 edge"
    assert tof_pixel_label(RIG, (10.0, 10.0)) == ""


def test_default_head_distance_error_thresholds(head_41, head_15) -> None:
    """Of the order of the method's Table 1 (CCD x about 2.4 m, thermal x about 1.3 m with
    41 mm); our head differs, so sane ranges."""
    assert head_41.sensors == (*CCD, *THERMAL)
    for key in head_41.distance_error:
        r41, r15 = head_41.distance_error[key], head_15.distance_error[key]
        for s in CCD:
            assert 1.8 < r41[s].x_m < 3.5
            assert 1.0 < r41[s].y_m < 3.0  # 3 cm above the TOF
        for s in THERMAL:
            assert 0.8 < r41[s].x_m < 2.0
        for s in (*CCD, *THERMAL):
            assert min(r41[c].x_m for c in CCD) > max(r41[t].x_m for t in THERMAL)
            for axis in ("x_m", "y_m"):
                a41, a15 = getattr(r41[s], axis), getattr(r15[s], axis)
                if a41 is None:
                    assert a15 is None
                elif a15 is not None:
                    assert a15 < a41


def test_thermal_at_the_tofs_height_has_no_significant_y_shift(head_41) -> None:
    """Table 1 has no y threshold for the thermal imagers. Ours sit 1 mm off the TOF's
    height and are tilted by up to 2 degrees 1 cm behind it, so |dy| crosses 0.5 px only
    right at the near end of the range (about 0.1-0.2 m), nothing like the colour cameras'
    1.8 m."""
    for per_sensor in head_41.distance_error.values():
        for s in THERMAL:
            assert per_sensor[s].y_m is None or per_sensor[s].y_m < 0.25
            far = per_sensor[s].distance_m >= 0.3
            assert np.all(np.abs(per_sensor[s].dy_px[far]) < 0.5)


def test_thermal_exactly_at_the_tofs_height_has_no_y_threshold() -> None:
    """A thermal imager exactly at the TOF's height and parallel to it: y_m None."""
    rig = default_rig()
    for s in THERMAL:
        t = rig[s].T_rig_sensor[:3, 3].copy()
        t[1] = 0.0
        rig.sensors[s].T_rig_sensor = make_T(np.eye(3), t)
    a = analyze_precision(rig)
    for per_sensor in a.distance_error.values():
        for s in THERMAL:
            assert per_sensor[s].y_m is None
            # only tangential distortion is left (of the TOF: y != 0 off axis; of the
            # thermal imager: p1 x^2): hundredths of a pixel
            assert np.max(np.abs(per_sensor[s].dy_px)) < 0.1


def test_default_head_tof_pixel_error(head_41) -> None:
    """Half a TOF pixel moves the point by about f_s / f_tof * 0.5 px at any distance:
    about 4 px in the colour cameras, 1.2 px in the thermal imagers (the method: 5 and
    1.5), so above 0.5 px over the whole range."""
    f_tof = RIG["tof"].intrinsics.fx
    for per_sensor in head_41.tof_pixel_error.values():
        for s in (*CCD, *THERMAL):
            expected = RIG[s].intrinsics.fx / f_tof * 0.5
            # (off axis the distortion of both cameras changes it by a few per cent)
            assert per_sensor[s].dx_px[-1] == pytest.approx(expected, rel=0.1)
            assert per_sensor[s].x_m == 10.0
    principal = head_41.tof_pixel_error[pixel_key(default_tof_pixels(RIG)[0])]
    for s in (*CCD, *THERMAL):
        assert principal[s].y_m is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"distance_error_m": -0.01}, "distance_error_m"),
        ({"tof_pixel_error_px": -0.5}, "tof_pixel_error_px"),
        ({"threshold_px": 0.0}, "threshold_px"),
        ({"tof_pixels": [(500.0, 10.0)]}, "outside"),
        ({"tof_pixels": [(1.0, 2.0, 3.0)]}, "expected"),
        ({"tof_pixels": []}, "at least one"),
        ({"distance_m": [1.0]}, "distance_m"),
    ],
)
def test_analyze_precision_rejects_bad_input(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        analyze_precision(RIG, **kwargs)


def test_rig_without_tof_is_an_error() -> None:
    s = RIG["ccd_left"]
    rig = Rig(
        sensors={"cam": Sensor("cam", "color", s.image_size, s.intrinsics, np.eye(4))},
        reference="cam",
    )
    with pytest.raises(ValueError, match="modality 'tof'"):
        analyze_precision(rig)


# -- the command line ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_rig(tmp_path_factory.mktemp("rig") / "rig.yaml", default_rig())


def test_cli_json_has_exactly_the_documented_shape(
    rig_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(
        ["analyze", str(rig_file), "--distance-error-mm", "41", "--threshold-px", "0.5", "--json"],
        capsys,
    )
    assert code == 0, err
    data = json.loads(out)
    assert set(data) == {"distance_error", "tof_pixel_error"}
    keys = [pixel_key(p) for p in default_tof_pixels(RIG)]
    assert keys == ["87.9,71.2", "157,71.2"]
    for kind in data.values():
        assert list(kind) == keys
        for per_sensor in kind.values():
            assert list(per_sensor) == [*CCD, *THERMAL]
            for entry in per_sensor.values():
                assert set(entry) == {"x_m", "y_m", "curve"}
                for k in ("x_m", "y_m"):
                    assert entry[k] is None or isinstance(entry[k], float)
                assert set(entry["curve"]) == {"distance_m", "dx_px", "dy_px"}
                for values in entry["curve"].values():
                    assert len(values) == 991
                    assert all(isinstance(x, float) for x in values)
                assert entry["curve"]["distance_m"][0] == 0.1
                assert entry["curve"]["distance_m"][-1] == 10.0
    # same numbers as the core
    a = analyze_precision(RIG)
    ccd = data["distance_error"][keys[0]]["ccd_left"]
    assert ccd["x_m"] == pytest.approx(a.distance_error[keys[0]]["ccd_left"].x_m, abs=1e-6)
    assert data["tof_pixel_error"][keys[0]]["ccd_left"]["x_m"] == 10.0


def test_cli_tof_pixels_replace_the_defaults(
    rig_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(
        [
            "analyze",
            str(rig_file),
            "--tof-pixel",
            "88,72",
            "--tof-pixel",
            "20.5,30",
            "--tof-pixel-error",
            "1",
            "--step-m",
            "0.1",
            "--json",
        ],
        capsys,
    )
    assert code == 0, err
    data = json.loads(out)
    assert list(data["distance_error"]) == ["88,72", "20.5,30"]
    assert list(data["tof_pixel_error"]) == ["88,72", "20.5,30"]
    assert len(data["distance_error"]["88,72"]["ccd_left"]["curve"]["distance_m"]) == 100


def test_cli_prints_the_table(rig_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_cli(["analyze", str(rig_file), "--distance-error-mm", "15"], capsys)
    assert code == 0, err
    for word in (*CCD, *THERMAL, "principal point", "region 3 edge", "distance error 15 mm"):
        assert word in out
    assert "TOF pixel error 0.5 px" in out
    assert "–" in out and "≥10.00" in out
    x_row = next(line for line in out.splitlines() if "distance error 15 mm" in line)
    values = [float(c) for c in x_row.split()[-4:]]
    a = analyze_precision(RIG, distance_error_m=0.015)
    first = next(iter(a.distance_error.values()))
    np.testing.assert_allclose(values, [first[s].x_m for s in (*CCD, *THERMAL)], atol=0.006)


def test_cli_plot(rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plot = tmp_path / "out.png"
    code, out, err = run_cli(["analyze", str(rig_file), "--plot", str(plot)], capsys)
    assert code == 0, err
    assert str(plot) in out
    assert plot.stat().st_size > 0
    image = cv2.imread(str(plot), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[0] > 500 and image.shape[1] > 500
    packed = image.astype(np.int32) @ np.array([1 << 16, 1 << 8, 1], np.int32)
    assert np.unique(packed).size > 10  # curves in colour, not a blank canvas
    # never overwritten
    code, _, err = run_cli(["analyze", str(rig_file), "--plot", str(plot)], capsys)
    assert code == 2 and "exists" in err


def _no_tof_rig(path: Path) -> Path:
    s = RIG["ccd_left"]
    rig = Rig(
        sensors={"cam": Sensor("cam", "color", s.image_size, s.intrinsics, np.eye(4))},
        reference="cam",
    )
    path.write_text(rig_to_yaml(rig))
    return path


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--tof-pixel", "1;2"], "U,V"),
        (["--tof-pixel", "a,b"], "U,V"),
        (["--tof-pixel", "1,2,3"], "U,V"),
        (["--tof-pixel", "nan,2"], "finite"),
        (["--tof-pixel", "500,10"], "outside"),
        (["--distance-error-mm", "-1"], ">= 0"),
        (["--tof-pixel-error", "-0.5"], ">= 0"),
        (["--threshold-px", "0"], "> 0"),
        (["--step-m", "0"], "> 0"),
        (["--step-m", "1e-9"], "--step-m"),
        (["--tof", "nope"], "nope"),
    ],
)
def test_cli_bad_arguments_exit_2(
    rig_file: Path, extra: list[str], match: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(["analyze", str(rig_file), *extra], capsys)
    assert code == 2
    assert match in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err and out == ""


def test_cli_bad_rig_files_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    malformed = tmp_path / "bad.yaml"
    malformed.write_text("format: trifuse-rig/1\nsensors: [1, 2\n")
    cases = [
        (tmp_path / "missing.yaml", "cannot read"),
        (malformed, "YAML"),
        (_no_tof_rig(tmp_path / "no_tof.yaml"), "modality 'tof'"),
    ]
    for path, match in cases:
        code, out, err = run_cli(["analyze", str(path)], capsys)
        assert code == 2, path
        assert match in err and str(path) in err
        assert out == ""
        assert len(err.strip().splitlines()) == 1
        assert "Traceback" not in err


def test_cli_help_mentions_the_options(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(["analyze", "--help"], capsys)
    assert code == 0
    for word in (
        "--distance-error-mm",
        "--tof-pixel-error",
        "--threshold-px",
        "--tof-pixel",
        "--json",
        "--plot",
    ):
        assert word in out
