"""The rig as a Kalibr camchain (calib.rig_formats.kalibr_format, issue 21): what Kalibr's
reader requires, the T_cn_cnm1 direction, exact round trips, what is lost (and how far a
dropped k3 moves a corner), a real camchain, and a thermal + TOF camchain that fuses."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import yaml

from tests.support import DATA_DIR, small_rig, synth_frame
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Eye, Rig, Sensor, rig_from_yaml, rig_to_yaml
from trifuse.calib.rig_formats import export_rig, import_rig
from trifuse.calib.rig_formats.kalibr_format import CAMCHAIN_NAME, export, import_, radtan_loss
from trifuse.calib.transforms import invert, make_T, rotation_from_euler_deg, transform_points

DATA = DATA_DIR / "rig_formats" / "kalibr"
EUROC = DATA / "euroc_camchain.yaml"
EYES = {"left": ("ccd_left", "thermal_left"), "right": ("ccd_right", "thermal_right")}


def camchain(rig: Rig, **options: Any) -> dict[str, Any]:
    return yaml.safe_load(export(rig, **options).files[CAMCHAIN_NAME])


def _eight(intrinsics: Intrinsics) -> np.ndarray:
    """The distortion coefficients k1 k2 p1 p2 k3 k4 k5 k6, zero-padded to 8."""
    return np.pad(intrinsics.dist, (0, 8 - len(intrinsics.dist)))


def assert_same_rig(got: Rig, want: Rig, tol: float = 1e-9, skip_distortion: tuple = ()) -> None:
    """Same sensors in the same order, reference, eyes, modalities, sizes, intrinsics
    (distortion compared zero-padded) and poses within ``tol``."""
    assert got.names == want.names and got.reference == want.reference
    assert got.eyes == want.eyes
    for name in want.names:
        g, w = got[name], want[name]
        assert (g.modality, g.image_size) == (w.modality, w.image_size), name
        gi, wi = g.intrinsics, w.intrinsics
        assert (gi.fx, gi.fy, gi.cx, gi.cy) == (wi.fx, wi.fy, wi.cx, wi.cy), name
        if name not in skip_distortion:
            np.testing.assert_array_equal(_eight(gi), _eight(wi), err_msg=name)
        np.testing.assert_allclose(g.T_rig_sensor, w.T_rig_sensor, atol=tol, err_msg=name)


# -- what Kalibr reads --------------------------------------------------------------------------


def kalibr_reader_problems(data: Any) -> list[str]:
    """What ethz-asl/kalibr's reader (aslam_offline_calibration/kalibr/python/kalibr_common/
    ConfigReader.py, CameraChainParameters and CameraParameters) would refuse: its checks,
    transcribed."""
    problems = []
    n = len(data)  # numCameras(): every top-level key is a camera
    for i in range(n):
        cam = data.get(f"cam{i}")
        if cam is None:
            return [f"cam{i} missing"]
        if not isinstance(cam["rostopic"], str):
            problems.append("rostopic has to be a string")
        model, intr = cam["camera_model"], cam["intrinsics"]
        if model != "pinhole" or len(intr) != 4:
            problems.append(f"cam{i}: invalid intrinsics for pinhole")
        if not all(isinstance(v, float) for v in intr) or min(intr) < 0.0:
            problems.append(f"cam{i}: invalid focalLength / principalPoint (floats >= 0)")
        counts = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}
        if len(cam["distortion_coeffs"]) != counts[cam["distortion_model"]]:
            problems.append(f"cam{i}: wrong number of distortion coefficients")
        res = cam["resolution"]
        if len(res) != 2 or not all(isinstance(v, int) for v in res):
            problems.append(f"cam{i}: invalid resolution")
        if any(j >= n for j in cam["cam_overlaps"]):
            problems.append(f"cam{i}: out-of-range camera id in cam_overlaps")
        if i > 0 and np.asarray(cam["T_cn_cnm1"], dtype=float).shape != (4, 4):
            problems.append(f"cam{i}: invalid camera baseline")
    return problems


def test_the_export_is_a_camchain_kalibr_reads() -> None:
    rig = default_rig()
    data = camchain(rig)
    assert kalibr_reader_problems(data) == []
    assert list(data) == ["cam0", "cam1", "cam2", "cam3", "cam4"]  # nothing else at the top
    order = ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
    for i, name in enumerate(order):  # the reference first, then the rig's order
        cam = data[f"cam{i}"]
        keys = {"cam_overlaps", "camera_model", "distortion_coeffs", "distortion_model",
                "intrinsics", "resolution", "rostopic"}  # fmt: skip
        keys |= {"T_cn_cnm1"} if i else set()
        assert set(cam) == keys
        s = rig[name]
        assert cam["rostopic"] == f"/{name}/image_raw"
        assert cam["intrinsics"] == [
            s.intrinsics.fx,
            s.intrinsics.fy,
            s.intrinsics.cx,
            s.intrinsics.cy,
        ]
        assert cam["distortion_model"] == "radtan"
        assert cam["distortion_coeffs"] == list(s.intrinsics.distortion[:4])
        assert cam["resolution"] == list(s.image_size)
        assert cam["cam_overlaps"] == [j for j in range(5) if j != i]
        if i:
            np.testing.assert_allclose(cam["T_cn_cnm1"], rig.T(name, order[i - 1]), atol=1e-15)


def test_t_cn_cnm1_maps_the_previous_camera_into_this_one() -> None:
    """A camera 0.1 m to the right of the reference (+x, OpenCV frames): a point at the
    reference's origin is 0.1 m to the left in it, so T_c1_c0 translates by -0.1 in x
    (EuRoC's right camera: -0.110 m, tests/data/rig_formats/kalibr/README.md)."""
    K = Intrinsics(400.0, 400.0, 319.5, 239.5, (0.0,) * 5)
    R = rotation_from_euler_deg(0.0, 5.0, 0.0)  # turned about y (yaw in camera terms)
    sensors = {
        "ccd_left": Sensor("ccd_left", "color", (640, 480), K, np.eye(4)),
        "ccd_right": Sensor("ccd_right", "color", (640, 480), K, make_T(R, [0.1, 0.0, 0.0])),
    }
    rig = Rig(sensors, "ccd_left")
    T = np.asarray(camchain(rig)["cam1"]["T_cn_cnm1"])
    np.testing.assert_allclose(T[:3, 3], -R.T @ [0.1, 0.0, 0.0], atol=1e-15)
    p_c0 = np.array([0.3, -0.2, 2.0])  # a point 2 m in front of cam0
    p_c1 = invert(sensors["ccd_right"].T_rig_sensor) @ np.append(p_c0, 1.0)
    np.testing.assert_allclose(transform_points(T, p_c0), p_c1[:3], atol=1e-15)


def test_dispatch_through_the_package() -> None:
    rig = default_rig()
    assert export_rig(rig, "kalibr").files == export(rig).files
    assert import_rig(export(rig).files, "kalibr").rig.names == rig.names


# -- round trips --------------------------------------------------------------------------------


def test_round_trip_of_the_simulated_head_is_exact() -> None:
    rig = default_rig()
    assert all(s.intrinsics.distortion[4:] == (0.0,) for s in rig.sensors.values())
    exported = export(rig)
    assert not any("distortion" in item for item in exported.lost)
    assert any(item.startswith("eyes (left: ccd_left + thermal_left") for item in exported.lost)
    assert any(item.startswith("modality: a camchain has none") for item in exported.lost)
    imported = import_(exported.files, eyes=EYES)
    assert_same_rig(imported.rig, rig, tol=1e-12)
    # the distortion comes back as OpenCV's five coefficients, exactly the rig's
    assert all(imported.rig[n].intrinsics == rig[n].intrinsics for n in rig.names)
    # and the imported rig is a rig file that loads
    assert_same_rig(rig_from_yaml(rig_to_yaml(imported.rig)), rig, tol=1e-12)
    lost = "\n".join(imported.lost)
    assert "range_correction of tof" in lost and "radiometry of thermal_left" in lost
    assert "eyes" not in lost  # they were given


def test_without_eyes_the_import_says_so() -> None:
    imported = import_(export(default_rig()).files)
    assert imported.rig.eyes == {}
    assert any(item.startswith("eyes: a camchain has none") for item in imported.lost)


def test_radiometry_range_correction_and_uncertainty_are_lost() -> None:
    from tests.fuzz_support import rich_rig

    rig = rich_rig()  # the simulated head with every optional block
    lost = "\n".join(export(rig).lost)
    assert "range correction of tof: a camchain has none" in lost
    assert "radiometry of thermal_left: a camchain has none" in lost
    assert "uncertainty of ccd_left: a camchain has none" in lost
    back = import_(export(rig).files, eyes=EYES).rig
    assert back["tof"].range_correction is None and back["thermal_left"].radiometry is None
    assert back["ccd_left"].uncertainty is None


# -- k3 and the rational terms ------------------------------------------------------------------


def k3_rig() -> Rig:
    """The simulated head with a colour camera whose k3 is typical of OpenCV's 5-term fit."""
    rig = default_rig()
    s = rig["ccd_left"]
    i = s.intrinsics
    dist = (i.distortion[0], i.distortion[1], i.distortion[2], i.distortion[3], 0.02)
    intr = Intrinsics(i.fx, i.fy, i.cx, i.cy, dist)
    return rig.with_sensor(Sensor(s.name, s.modality, s.image_size, intr, s.T_rig_sensor))


def corner_shift_by_projection(sensor: Sensor) -> tuple[tuple[float, float], float]:
    """The farthest corner and how far the four-term model moves it, measured another way:
    the full model's ray through the corner, projected by the four-term camera."""
    i = sensor.intrinsics
    w, h = sensor.image_size
    corners = [(0.0, 0.0), (w - 1.0, 0.0), (0.0, h - 1.0), (w - 1.0, h - 1.0)]
    corner = max(corners, key=lambda c: np.hypot(c[0] - i.cx, c[1] - i.cy))
    ray = i.unproject(np.array(corner))
    four = Intrinsics(i.fx, i.fy, i.cx, i.cy, i.distortion[:4])
    return corner, float(np.linalg.norm(four.project(ray) - np.array(corner)))


def test_a_dropped_k3_is_lost_with_its_corner_shift() -> None:
    rig = k3_rig()
    corner, shift = corner_shift_by_projection(rig["ccd_left"])
    loss = radtan_loss(rig["ccd_left"])
    assert loss is not None and loss.dropped == {"k3": 0.02}
    assert loss.corner_px == corner == (0.0, 959.0)  # cx = 641.3: the left corners
    assert loss.shift_px == pytest.approx(shift, rel=1e-9)
    assert 0.9 < shift < 1.1  # pixels, at the corner of a 1280 x 960 image: not negligible
    exported = export(rig)
    (item,) = [x for x in exported.lost if x.startswith("distortion of ccd_left")]
    assert "k3 = 0.02 dropped" in item and f"by {shift:.3g} px" in item
    assert yaml.safe_load(exported.files[CAMCHAIN_NAME])["cam1"]["distortion_coeffs"] == list(
        rig["ccd_left"].intrinsics.distortion[:4]
    )
    # round trip: everything else exact, k3 now zero
    back = import_(exported.files, eyes=EYES).rig
    assert_same_rig(back, rig, tol=1e-12, skip_distortion=("ccd_left",))
    assert back["ccd_left"].intrinsics.distortion == (
        *rig["ccd_left"].intrinsics.distortion[:4],
        0.0,
    )


def test_rational_terms_are_lost_too() -> None:
    rig = small_rig()  # thermal_right has k3 and k4..k6
    corner, shift = corner_shift_by_projection(rig["thermal_right"])
    (item,) = [x for x in export(rig).lost if x.startswith("distortion of thermal_right")]
    assert "k3 = 0.001, k4 = 0.01, k5 = -0.002, k6 = 0.0005 dropped" in item
    assert f"({corner[0]:g}, {corner[1]:g}) by {shift:.3g} px" in item


def test_strict_refuses_naming_the_sensor_and_the_shift() -> None:
    rig = k3_rig()
    _, shift = corner_shift_by_projection(rig["ccd_left"])
    with pytest.raises(ValueError, match=rf"ccd_left.*k3 = 0\.02.*{shift:.3g} px"):
        export(rig, strict=True)
    export(default_rig(), strict=True)  # nothing to drop: no refusal


def test_topics_option() -> None:
    rig = default_rig()
    data = camchain(rig, topics={"thermal_left": "/lwir/left/image_raw"})
    assert data["cam3"]["rostopic"] == "/lwir/left/image_raw"
    lost = "\n".join(export(rig, topics={"thermal_left": "/lwir/left/image_raw"}).lost)
    assert "name of thermal_left" in lost and "modality of thermal_left (thermal)" in lost
    lost = "\n".join(export(rig, topics={"tof": "/tof-main/image_raw"}).lost)
    assert "rostopic of tof: /tof-main/image_raw is not a valid ROS topic name" in lost
    with pytest.raises(ValueError, match="topics: no sensor"):
        export(rig, topics={"nope": "/x"})
    with pytest.raises(ValueError, match="expected a ROS topic"):
        export(rig, topics={"tof": "tof"})


# -- a real camchain ----------------------------------------------------------------------------


def test_the_real_euroc_camchain_is_refused_for_its_fisheye_lenses() -> None:
    with pytest.raises(RigError, match=r"euroc_camchain\.yaml: cam0\.distortion_model: "
                                       r"'equidistant' cannot be imported"):  # fmt: skip
        import_({EUROC.name: EUROC.read_text()}, names={0: "ccd_left", 1: "ccd_right"})


def test_the_real_euroc_camchain_geometry() -> None:
    """The real file with its two lens models declared ``none`` (all else as Kalibr wrote
    it): the numbers come through exactly and the chained pose is the file's baseline."""
    text = EUROC.read_text()
    raw = yaml.safe_load(text)
    assert text.count("distortion_model: equidistant") == 2
    text = text.replace("distortion_model: equidistant", "distortion_model: none")
    text = text.replace("distortion_coeffs:", "old_coeffs:")  # not Kalibr's: ignored, said
    imported = import_({EUROC.name: text}, names={0: "ccd_left", 1: "ccd_right"})
    rig = imported.rig
    assert rig.names == ["ccd_left", "ccd_right"] and rig.reference == "ccd_left"
    for name, cam in zip(rig.names, ("cam0", "cam1"), strict=True):
        s = rig[name]
        assert s.modality == "color"
        assert [s.intrinsics.fx, s.intrinsics.fy, s.intrinsics.cx, s.intrinsics.cy] == raw[cam][
            "intrinsics"
        ]
        assert list(s.image_size) == raw[cam]["resolution"] == [752, 480]
        assert s.intrinsics.distortion == (0.0,) * 5
    T_c1_c0 = np.array(raw["cam1"]["T_cn_cnm1"])
    np.testing.assert_array_equal(rig["ccd_left"].T_rig_sensor, np.eye(4))
    np.testing.assert_allclose(rig.T("ccd_right", "ccd_left"), T_c1_c0, atol=1e-15)
    np.testing.assert_allclose(rig["ccd_right"].T_rig_sensor, invert(T_c1_c0), atol=1e-15)
    # Kalibr's convention on real data: T_cn_cnm1 = T_c1_imu inv(T_c0_imu) ...
    T_c0_imu, T_c1_imu = (np.array(raw[c]["T_cam_imu"]) for c in ("cam0", "cam1"))
    np.testing.assert_allclose(rig.T("ccd_right", "ccd_left"), T_c1_imu @ invert(T_c0_imu),
                               atol=1e-12)  # fmt: skip
    # ... and the right camera sits 0.110 m to the right (+x) of the left one
    baseline = rig["ccd_right"].T_rig_sensor[:3, 3]
    assert baseline[0] == pytest.approx(0.1100, abs=5e-4) and np.linalg.norm(baseline) < 0.111
    lost = "\n".join(imported.lost)
    for said in ("T_cam_imu of cam0: ignored (a trifuse rig has no IMU)",
                 "flip_camera of cam1: not a key of Kalibr's camchain; ignored",
                 "old_coeffs of cam0: not a key of Kalibr's camchain; ignored",
                 "modalities (a camchain has none) from the names: ccd_left color, "
                 "ccd_right color", "eyes: a camchain has none"):  # fmt: skip
        assert said in lost
    assert "cam_overlaps" not in lost


def test_names_default_to_the_rostopics() -> None:
    text = EUROC.read_text().replace("distortion_model: equidistant", "distortion_model: none")
    text = text.replace("distortion_coeffs:", "old_coeffs:")
    imported = import_({EUROC.name: text}, modalities={"cam1": "thermal"})
    assert imported.rig.names == ["cam0", "cam1"]
    assert [imported.rig[n].modality for n in ("cam0", "cam1")] == ["color", "thermal"]
    assert (
        "sensor names from the rostopics: cam0 cam0 <- /cam0/image_raw, "
        "cam1 cam1 <- /cam1/image_raw"
    ) in imported.lost
    assert "radiometry of cam1: a camchain has none; raw values read as kelvin" in imported.lost


# -- a thermal + TOF camchain that fuses --------------------------------------------------------


def test_a_thermal_and_tof_camchain_with_eyes_fuses() -> None:
    """A camchain of the small head (cam0 the TOF camera, two colour cameras, two thermal
    imagers, topics /thermal_left/image_raw ...), imported with eyes: the fusion that
    `trifuse serve --rig` runs takes it and fuses a frame set."""
    from trifuse.fusion.compose import DisplaySettings
    from trifuse.fusion.stereo import StereoFusion

    source = small_rig()
    text = export(source).files[CAMCHAIN_NAME]
    assert "rostopic: /thermal_left/image_raw" in text and "rostopic: /tof/image_raw" in text
    imported = import_({"head-camchain.yaml": text}, eyes=EYES)
    rig = imported.rig
    assert rig.reference == "tof"
    assert {n: rig[n].modality for n in rig.names} == {n: source[n].modality for n in source.names}
    assert rig.eyes == {"left": Eye("ccd_left", "thermal_left"),
                        "right": Eye("ccd_right", "thermal_right")}  # fmt: skip
    fusion = StereoFusion(rig)
    rng = np.random.default_rng(0)
    stamp = 1_000_000_000
    tof = synth_frame(rig, "tof", stamp, rng)
    fusion.update_depth(tof.distance_m, tof.image)
    assert fusion.ready
    colors = {e: synth_frame(rig, rig.eyes[e].color, stamp, rng).image for e in EYES}
    thermals = {e: synth_frame(rig, rig.eyes[e].thermal, stamp, rng).image for e in EYES}
    frame = fusion.compose(colors, thermals, DisplaySettings(), stamp)
    w, h = rig["ccd_left"].image_size
    assert frame.shape == (h, 2 * w, 3)
    for e in EYES:  # thermal values reached the colour pixels of both eyes
        warped = fusion.thermal_on_color[e]
        assert np.isfinite(warped).mean() > 0.3
        assert 285.0 < np.nanmedian(warped) < 315.0  # synth_frame's 290 .. 310 K


# -- malformed input ----------------------------------------------------------------------------

GOOD = export(small_rig()).files[CAMCHAIN_NAME]


def edited(change) -> str:
    data = yaml.safe_load(GOOD)
    change(data)
    return yaml.safe_dump(data)


def _set(cam: str, key: str, value: Any):
    return lambda d: d[cam].__setitem__(key, value)


MALFORMED = [
    ("not: [valid", "not valid YAML"),
    ("- cam0\n- cam1\n", "expected a mapping of cameras cam0, cam1, ..., got list"),
    (edited(lambda d: d.__setitem__("imu0", {})), "key 'imu0': expected only cam0, cam1"),
    (edited(lambda d: d.pop("cam2")), "cam2: missing"),
    (edited(lambda d: d["cam1"].pop("T_cn_cnm1")), "cam1: missing key(s) ['T_cn_cnm1']"),
    (edited(lambda d: d["cam0"].pop("intrinsics")), "cam0: missing key(s) ['intrinsics']"),
    (edited(_set("cam0", "camera_model", "omni")), "cam0.camera_model: 'omni' cannot be"),
    (edited(_set("cam3", "distortion_model", "equidistant")),
     "cam3.distortion_model: 'equidistant'"),
    (edited(_set("cam3", "distortion_model", "fov")), "cam3.distortion_model: 'fov'"),
    (edited(_set("cam3", "distortion_model", "plumb_bob")), "Kalibr's models are"),
    (edited(_set("cam0", "intrinsics", [1.0, 2.0, 3.0])), "cam0.intrinsics: expected 4 numbers"),
    (edited(_set("cam0", "intrinsics", [1.0, "a", 3.0, 4.0])),
     "cam0.intrinsics: expected 4 finite"),
    (edited(_set("cam0", "intrinsics", [-1.0, 2.0, 3.0, 4.0])), "cam0.intrinsics: focal lengths"),
    (edited(_set("cam1", "distortion_coeffs", [0.1] * 5)), "cam1.distortion_coeffs: expected 4"),
    (edited(_set("cam1", "distortion_model", "none")),
     "cam1.distortion_coeffs: distortion_model 'none' takes none"),
    (edited(_set("cam2", "resolution", [128.0, 96])), "cam2.resolution: expected [width, height]"),
    (edited(_set("cam2", "resolution", [100000, 100000])), "megapixels"),
    (edited(_set("cam2", "rostopic", 7)), "cam2.rostopic: expected a ROS topic"),
    (edited(_set("cam2", "T_cn_cnm1", [[1, 0, 0, 0]] * 4)),
     "cam2.T_cn_cnm1: not a rigid transform"),
    (edited(_set("cam2", "T_cn_cnm1", [[1, 0, 0]] * 3)), "cam2.T_cn_cnm1: expected a 4x4 list"),
    (edited(_set("cam2", "T_cn_cnm1", [[1, 0, 0]] * 4)), "cam2.T_cn_cnm1: expected 4 numbers"),
    (edited(_set("cam2", "T_cn_cnm1", "eye")), "cam2.T_cn_cnm1: expected a 4x4 list"),
    (edited(_set("cam2", "rostopic", "/ccd_left/image_raw")),
     "['ccd_left'] given to more than one"),
    (edited(_set("cam2", "rostopic", "/bad name/image_raw")), "sensor name 'bad name'"),
]  # fmt: skip


@pytest.mark.parametrize(("text", "match"), MALFORMED, ids=[m for _, m in MALFORMED])
def test_malformed_camchains_name_the_key(text: str, match: str) -> None:
    with pytest.raises(RigError) as info:
        import_({"camchain.yaml": text})
    assert str(info.value).startswith("camchain.yaml: ")
    assert match in str(info.value)


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"names": {7: "x"}}, "names: no camera [7] in the camchain (cam0 .. cam4)"),
        ({"modalities": {"nope": "color"}}, "modalities: no sensor(s) ['nope']"),
        ({"modalities": {"tof": "sonar"}}, "expected one of"),
        ({"reference": "nope"}, "reference: no sensor 'nope'"),
        ({"eyes": {"left": ("thermal_left", "ccd_left")}}, "eyes.left.color"),
        ({"eyes": {"left": ("ccd_left",)}}, "eyes.left: expected (colour sensor, thermal"),
    ],
)
def test_bad_options(options: dict[str, Any], match: str) -> None:
    with pytest.raises(RigError, match=None) as info:
        import_({"camchain.yaml": GOOD}, **options)
    assert match in str(info.value)


def test_reference_option_re_expresses_the_poses() -> None:
    rig = default_rig()
    got = import_(export(rig).files, eyes=EYES, reference="thermal_left").rig
    assert got.reference == "thermal_left"
    np.testing.assert_array_equal(got["thermal_left"].T_rig_sensor, np.eye(4))
    for a in rig.names:
        for b in rig.names:
            np.testing.assert_allclose(got.T(a, b), rig.T(a, b), atol=1e-12)


def test_which_file_is_the_camchain() -> None:
    files = {"cam-camchain.yaml": GOOD, "cam-results.txt": "Calibration results\n"}
    assert import_(files).rig.names == small_rig().names
    files = {"cam-camchain.yaml": GOOD, "cam-camchain-imucam.yaml": GOOD, "imu.yaml": "x: 1"}
    with pytest.raises(RigError, match="which camchain"):
        import_(files)
    with pytest.raises(RigError, match="no camchain"):
        import_({"a.txt": "", "b.txt": ""})
