"""The rig in ROS camera_info + URDF, OpenCV FileStorage and URDF (issue 21): round trips to
1e-9, what each format loses, the files as their own readers see them (xml.etree for the
URDF, yaml.safe_load with camera_calibration_parsers' keys for ROS, cv2.FileStorage for
OpenCV), a real camera_info file written by ROS's camera_calibration, and malformed input."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable

import cv2
import numpy as np
import pytest
import yaml

from tests.support import DATA_DIR
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import RigError
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.range_correction import RangeCorrection
from trifuse.calib.rig import Eye, Rig, Sensor
from trifuse.calib.rig_formats import (
    Exported,
    export_rig,
    import_rig,
    opencv_format,
    ros_format,
    urdf_format,
)
from trifuse.calib.transforms import (
    invert,
    make_T,
    rotation_from_euler_deg,
    rotation_from_rpy,
    rpy_from_rotation,
    transform_points,
)

ROS_SAMPLE = DATA_DIR / "rig_formats" / "ros" / "camera_info.yaml"
DEFAULT_EYES = {"left": ("ccd_left", "thermal_left"), "right": ("ccd_right", "thermal_right")}
TOL = 1e-9


# -- rigs -----------------------------------------------------------------------------------


def _pose(rng: np.random.Generator, roll: float, pitch: float, yaw: float) -> np.ndarray:
    return make_T(rotation_from_euler_deg(roll, pitch, yaw), rng.uniform(-0.2, 0.2, 3))


def varied_rig() -> Rig:
    """Every distortion length (4, 5 with k3, 8 rational, 8 with k4-k6 zero), sensors
    pitched +-90 degrees (gimbal lock), and every block a format may lose."""
    rng = np.random.default_rng(21)
    tof_size = (176, 144)
    range_block = {
        "model": "trifuse-range/1",
        "distance": {"start_m": 0.5, "step_m": 0.25, "coeffs_m": [0.03, 0.02, 0.01, 0.02, 0.03]},
        "offset": {
            "step_px": 8,
            "nodes_m": [[0.001 * (r - c) for c in range(23)] for r in range(19)],
        },
        "amplitude": {"ref": 1500.0, "log_range": [-1.0, 1.0], "coeffs_m": [0.004, -0.001]},
    }
    sensors = [
        Sensor(
            "tof",
            "tof",
            tof_size,
            Intrinsics(165.5, 165.8, 87.9, 71.2, (-0.12, 0.05, 0.0003, -0.0002)),
            np.eye(4),
            uncertainty={"fx": 0.4},
            range_correction=RangeCorrection.from_dict(range_block, tof_size),
        ),
        Sensor(
            "ccd_k3",
            "color",
            (1920, 1080),
            Intrinsics(1401.25, 1399.5, 959.3, 541.1, (-0.21, 0.13, 1e-05, -2.5e-4, -0.031)),
            _pose(rng, 3.0, -2.0, 1.0),
        ),
        Sensor(
            "thermal_rational",
            "thermal",
            (640, 512),
            Intrinsics(512.3, 511.9, 319.2, 255.8, (0.8, -0.12, 3e-4, 1e-4, 0.05, 1.1, 0.2, 0.07)),
            _pose(rng, 30.0, 90.0, -40.0),
            radiometry=Radiometry(gain=1.02, offset_k=-0.3),
        ),
        Sensor(
            "rgb_zero_tail",
            "color",
            (800, 600),
            Intrinsics(700.0, 701.0, 399.5, 299.5, (-0.1, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)),
            _pose(rng, -120.0, -90.0, 75.0),
        ),
        Sensor(
            "lwir_side",
            "thermal",
            (382, 288),
            Intrinsics(402.1, 401.5, 191.8, 142.7, (-0.21, 0.11, 0.0006, -0.0004, 0.0)),
            _pose(rng, 170.0, 89.9999999, -179.0),
        ),
    ]
    return Rig(
        sensors={s.name: s for s in sensors},
        reference="tof",
        eyes={"one": Eye("ccd_k3", "thermal_rational")},
    )


def padded(distortion: tuple[float, ...]) -> list[float]:
    return (list(distortion) + [0.0] * 8)[:8]


def assert_same_rig(got: Rig, want: Rig, *, eyes: bool = True) -> None:
    """Same sensors in the same order, modality, size, intrinsics and distortion (up to
    zero padding) exactly, poses to 1e-9, reference, and the eyes when ``eyes``."""
    assert got.names == want.names
    assert got.reference == want.reference
    for name in want.names:
        g, w = got[name], want[name]
        assert g.modality == w.modality, name
        assert g.image_size == w.image_size, name
        gi, wi = g.intrinsics, w.intrinsics
        assert (gi.fx, gi.fy, gi.cx, gi.cy) == (wi.fx, wi.fy, wi.cx, wi.cy), name
        assert padded(gi.distortion) == padded(wi.distortion), name
        np.testing.assert_allclose(g.T_rig_sensor, w.T_rig_sensor, rtol=0, atol=TOL, err_msg=name)
    assert np.array_equal(got[got.reference].T_rig_sensor, np.eye(4))
    if eyes:
        assert got.eyes == want.eyes


# -- URDF -----------------------------------------------------------------------------------


def urdf_origin_T(joint: ET.Element) -> np.ndarray:
    """A joint's origin as (4, 4), computed independently of urdf_format: URDF's rpy is
    the fixed-axis Rz(yaw) Ry(pitch) Rx(roll), which is rotation_from_euler_deg's order."""
    origin = joint.find("origin")
    xyz = [float(v) for v in origin.get("xyz").split()]
    roll, pitch, yaw = (math.degrees(float(v)) for v in origin.get("rpy").split())
    return make_T(rotation_from_euler_deg(roll, pitch, yaw), xyz)


@pytest.mark.parametrize("make_rig", [default_rig, varied_rig], ids=["default", "varied"])
def test_urdf_joints_reproduce_every_pose(make_rig: Callable[[], Rig]) -> None:
    rig = make_rig()
    exported = urdf_format.export(rig)
    assert list(exported.files) == ["trifuse_head.urdf"]
    root = ET.fromstring(exported.files["trifuse_head.urdf"])
    assert root.tag == "robot" and root.get("name") == "trifuse_head"
    links = [link.get("name") for link in root.findall("link")]
    assert links == ["rig"] + [f"{n}_optical_frame" for n in rig.names]
    joints = root.findall("joint")
    assert len(joints) == len(rig.names)
    for joint, name in zip(joints, rig.names, strict=True):
        assert joint.get("type") == "fixed"
        assert joint.get("name") == f"{name}_optical_frame_joint"
        assert joint.find("parent").get("link") == "rig"
        assert joint.find("child").get("link") == f"{name}_optical_frame"
        np.testing.assert_allclose(
            urdf_origin_T(joint), rig[name].T_rig_sensor, rtol=0, atol=TOL, err_msg=name
        )


def test_urdf_sensor_pitched_90_degrees() -> None:
    """At gimbal lock only roll - yaw is defined: the joint still gives the exact rotation,
    and a point seen by the sensor lands where the rig says."""
    R = rotation_from_euler_deg(25.0, 90.0, -70.0)
    T = make_T(R, [0.1, -0.02, 0.3])
    tof = default_rig()["tof"]
    rig = Rig(
        {
            "tof": tof,
            "thermal_down": Sensor("thermal_down", "thermal", (382, 288), tof.intrinsics, T),
        },
        "tof",
    )
    joint = ET.fromstring(urdf_format.export(rig).files["trifuse_head.urdf"]).findall("joint")[1]
    _, pitch, yaw = (float(v) for v in joint.find("origin").get("rpy").split())
    assert pitch == pytest.approx(math.pi / 2, abs=1e-12)
    assert yaw == 0.0  # folded into roll
    np.testing.assert_allclose(urdf_origin_T(joint), T, rtol=0, atol=1e-12)
    P = np.random.default_rng(3).uniform(-1, 1, (10, 3))
    np.testing.assert_allclose(
        transform_points(urdf_origin_T(joint), P), transform_points(T, P), rtol=0, atol=1e-12
    )


def test_rpy_round_trip_everywhere() -> None:
    rng = np.random.default_rng(7)
    angles = [tuple(rng.uniform(-180, 180, 3)) for _ in range(300)]
    for pitch in (90.0, -90.0, 90.0 - 1e-7, -90.0 + 1e-9, 89.9, 0.0, 180.0):
        angles += [(r, pitch, y) for r, y in rng.uniform(-180, 180, (20, 2))]
    for roll, pitch, yaw in angles:
        R = rotation_from_euler_deg(roll, pitch, yaw)
        rpy = rpy_from_rotation(R)
        assert -math.pi / 2 <= rpy[1] <= math.pi / 2
        np.testing.assert_allclose(rotation_from_rpy(*rpy), R, rtol=0, atol=1e-14)


def test_urdf_options_name_the_links() -> None:
    rig = default_rig()
    text = urdf_format.export(
        rig, robot_name="head2", base_link="head2_mount", prefix="head2/"
    ).files["head2.urdf"]
    root = ET.fromstring(text)
    assert root.get("name") == "head2"
    assert [j.find("parent").get("link") for j in root.findall("joint")] == ["head2_mount"] * 5
    assert root.findall("joint")[1].find("child").get("link") == "head2/ccd_left_optical_frame"
    prefixed = urdf_format.export(rig, prefix="h/").files["trifuse_head.urdf"]
    assert ET.fromstring(prefixed).find("link").get("name") == "h/rig"
    for bad in ({"robot_name": "two words"}, {"prefix": "a b"}, {"base_link": ""}):
        with pytest.raises(RigError, match="URDF option"):
            urdf_format.export(rig, **bad)


def test_urdf_lost_lists_everything_but_the_poses() -> None:
    lost = urdf_format.export(varied_rig()).lost
    text = "\n".join(lost)
    for part in (
        "intrinsics, distortion and image size of every sensor",
        "modality of every sensor",
        "radiometry of thermal_rational",
        "range correction of tof",
        "uncertainty of tof",
        "eyes (one)",
    ):
        assert part in text
    assert len(lost) == 6
    assert export_rig(varied_rig(), "urdf").lost == lost


def test_poses_from_urdf_and_chains() -> None:
    """A robot's URDF with the head on an intermediate link: T_parent_child per joint, and
    poses between links composed through the tree."""
    rng = np.random.default_rng(5)
    T_base_mount = _pose(rng, 0.0, 0.0, 90.0)
    T_mount_a = _pose(rng, 10.0, 20.0, 30.0)
    T_mount_b = _pose(rng, -5.0, 90.0, 12.0)

    def joint(name: str, kind: str, parent: str, child: str, T: np.ndarray) -> str:
        rpy = " ".join(repr(v) for v in rpy_from_rotation(T[:3, :3]))
        xyz = " ".join(repr(float(v)) for v in T[:3, 3])
        return (
            f'<joint name="{name}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="{child}"/><origin xyz="{xyz}" rpy="{rpy}"/></joint>'
        )

    text = (
        '<robot name="r"><link name="base_link"/>'
        + joint("pan", "revolute", "base_link", "mount", T_base_mount)
        + joint("ja", "fixed", "mount", "a_optical_frame", T_mount_a)
        + joint("jb", "fixed", "mount", "b_optical_frame", T_mount_b)
        + '<joint name="bare" type="fixed"><parent link="mount"/><child link="c"/></joint>'
        + "</robot>"
    )
    poses = urdf_format.poses_from_urdf(text)
    assert set(poses) == {"mount", "a_optical_frame", "b_optical_frame", "c"}
    np.testing.assert_allclose(poses["a_optical_frame"], T_mount_a, atol=1e-12)
    np.testing.assert_array_equal(poses["c"], np.eye(4))  # no <origin>: the identity
    joints = urdf_format.joints_from_urdf(text, "r.urdf")
    T_a_b = urdf_format.relative_pose(joints, "a_optical_frame", "b_optical_frame", "r.urdf")
    np.testing.assert_allclose(T_a_b, invert(T_mount_a) @ T_mount_b, atol=1e-12)
    ancestor, in_frame = urdf_format.common_frame_poses(
        joints, ["a_optical_frame", "b_optical_frame"], "r.urdf"
    )
    assert ancestor == "mount"
    np.testing.assert_allclose(in_frame["b_optical_frame"], T_mount_b, atol=1e-12)
    with pytest.raises(RigError, match=r"r\.urdf: joint 'pan' .* revolute, not fixed"):
        urdf_format.relative_pose(joints, "base_link", "a_optical_frame", "r.urdf")
    with pytest.raises(RigError, match="not connected"):
        urdf_format.relative_pose(joints, "a_optical_frame", "elsewhere", "r.urdf")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("<robot><joint", "not valid XML"),
        ("<model/>", "expected a <robot> root"),
        ('<robot><joint name="j" type="fixed"><child link="c"/></joint></robot>', "<parent"),
        (
            '<robot><joint name="j" type="hinge"><parent link="p"/><child link="c"/>'
            "</joint></robot>",
            "type",
        ),
        (
            '<robot><joint name="j" type="fixed"><parent link="p"/><child link="c"/>'
            '<origin xyz="1 2" rpy="0 0 0"/></joint></robot>',
            "origin xyz: expected three finite numbers",
        ),
        (
            '<robot><joint name="j" type="fixed"><parent link="p"/><child link="c"/>'
            '<origin xyz="1 2 nan"/></joint></robot>',
            "origin xyz",
        ),
        (
            '<robot><joint name="j" type="fixed"><parent link="p"/><child link="c"/></joint>'
            '<joint name="k" type="fixed"><parent link="q"/><child link="c"/></joint></robot>',
            "child of two joints",
        ),
        ('<!DOCTYPE r [<!ENTITY a "aaaa">]><robot>&a;</robot>', "document type"),
    ],
)
def test_malformed_urdf_names_the_file(text: str, match: str) -> None:
    with pytest.raises(RigError, match=match) as info:
        urdf_format.joints_from_urdf(text, "head.urdf")
    assert str(info.value).startswith("head.urdf: ")


def test_urdf_cannot_be_imported() -> None:
    with pytest.raises(ValueError, match="to import"):
        import_rig({"x.urdf": "<robot/>"}, "urdf")


# -- ROS ------------------------------------------------------------------------------------


def test_ros_files_are_what_camera_calibration_parsers_reads() -> None:
    """Each <sensor>.yaml has exactly the keys camera_calibration_parsers writes, in its
    order, every matrix with rows * cols values, and the sensor's numbers."""
    rig = varied_rig()
    exported = ros_format.export(rig)
    assert sorted(exported.files) == sorted(
        [f"{n}.yaml" for n in rig.names] + ["trifuse_head.urdf"]
    )
    models = {}
    for name, sensor in rig.sensors.items():
        data = yaml.safe_load(exported.files[f"{name}.yaml"])
        assert list(data) == list(ros_format.CAMERA_INFO_KEYS)
        assert data["image_width"] == sensor.width and data["image_height"] == sensor.height
        assert data["camera_name"] == name
        shapes = {
            "camera_matrix": (3, 3),
            "rectification_matrix": (3, 3),
            "projection_matrix": (3, 4),
        }
        for key in (*shapes, "distortion_coefficients"):
            block = data[key]
            assert set(block) == {"rows", "cols", "data"}
            assert block["rows"] * block["cols"] == len(block["data"])
            assert all(isinstance(v, float) for v in block["data"]), key
            if key in shapes:
                assert (block["rows"], block["cols"]) == shapes[key]
        K = np.reshape(data["camera_matrix"]["data"], (3, 3))
        np.testing.assert_array_equal(K, sensor.intrinsics.K)
        np.testing.assert_array_equal(
            np.reshape(data["rectification_matrix"]["data"], (3, 3)), np.eye(3)
        )
        P = np.reshape(data["projection_matrix"]["data"], (3, 4))
        np.testing.assert_array_equal(P, np.hstack([sensor.intrinsics.K, np.zeros((3, 1))]))
        D = data["distortion_coefficients"]
        assert D["rows"] == 1
        assert padded(tuple(D["data"])) == padded(sensor.intrinsics.distortion)
        models[name] = (data["distortion_model"], D["cols"])
    assert models == {
        "tof": ("plumb_bob", 5),
        "ccd_k3": ("plumb_bob", 5),
        "thermal_rational": ("rational_polynomial", 8),
        "rgb_zero_tail": ("plumb_bob", 5),
        "lwir_side": ("plumb_bob", 5),
    }
    assert "1.0e-05" in exported.files["ccd_k3.yaml"]  # YAML 1.1 readers need the dot


def test_ros_round_trip_default_rig() -> None:
    rig = default_rig()
    exported = export_rig(rig, "ros")
    assert exported.lost == [
        "eyes (left=(ccd_left, thermal_left), right=(ccd_right, thermal_right)): ROS has no "
        "eye pairs; pass eyes= to the import",
        "modality: camera_info has none; the import infers it from the name's prefix for "
        "tof, ccd_left, ccd_right, thermal_left, thermal_right",
    ]
    imported = import_rig(exported.files, "ros", eyes=DEFAULT_EYES)
    assert_same_rig(imported.rig, rig)
    assert all(line.startswith("modality of ") for line in imported.lost)
    assert len(imported.lost) == len(rig.names)
    without_eyes = ros_format.import_(exported.files)
    assert without_eyes.rig.eyes == {}
    assert any(
        line.startswith("eyes: ROS camera_info has no eye pairs") for line in without_eyes.lost
    )
    # Another root link and a prefix, as for a second head on a robot.
    moved = ros_format.export(rig, robot_name="h2", base_link="h2_mount", prefix="h2/").files
    assert "h2.urdf" in moved
    assert_same_rig(ros_format.import_(moved, eyes=DEFAULT_EYES, prefix="h2/").rig, rig)
    with pytest.raises(RigError, match=r"h2\.urdf: no joint places link 'tof_optical_frame'"):
        ros_format.import_(moved)
    # Links named as trifuse's recordings name the frames (frame_id = the sensor's name).
    plain = ros_format.export(rig, link_suffix="").files
    children = [
        j.find("child").get("link") for j in ET.fromstring(plain["trifuse_head.urdf"]).iter("joint")
    ]
    assert children == rig.names
    assert_same_rig(ros_format.import_(plain, eyes=DEFAULT_EYES, link_suffix="").rig, rig)
    # A URDF may be called .xml; other XML files (a launch file) are skipped.
    as_xml = {(k[:-5] + ".xml" if k.endswith(".urdf") else k): v for k, v in exported.files.items()}
    as_xml["camera.launch.xml"] = "<launch><node pkg='usb_cam'/></launch>"
    again = ros_format.import_(as_xml, eyes=DEFAULT_EYES)
    assert_same_rig(again.rig, rig)
    assert "camera.launch.xml: not a URDF (no <robot> root element); ignored" in again.lost
    # The order comes from the URDF, not from the order the files arrive in.
    shuffled = dict(sorted(exported.files.items(), reverse=True))
    assert_same_rig(ros_format.import_(shuffled, eyes=DEFAULT_EYES).rig, rig)


def test_ros_round_trip_k3_and_rational() -> None:
    rig = varied_rig()
    exported = ros_format.export(rig)
    text = "\n".join(exported.lost)
    for part in (
        "radiometry of thermal_rational",
        "range correction of tof",
        "uncertainty of tof",
        "eyes (one=(ccd_k3, thermal_rational))",
        "modality: camera_info has none",
    ):
        assert part in text
    imported = ros_format.import_(exported.files, eyes={"one": ("ccd_k3", "thermal_rational")})
    assert_same_rig(imported.rig, rig)
    assert (
        imported.rig["thermal_rational"].intrinsics.distortion
        == rig["thermal_rational"].intrinsics.distortion
    )
    assert imported.rig["tof"].range_correction is None
    assert imported.rig["thermal_rational"].radiometry is None


def test_ros_modality_from_the_option() -> None:
    base = default_rig()
    renamed = Rig(
        {
            "tof": base["tof"],
            "cam_ir": Sensor(
                "cam_ir",
                "thermal",
                (382, 288),
                base["thermal_left"].intrinsics,
                base["thermal_left"].T_rig_sensor,
            ),
        },
        "tof",
    )
    exported = ros_format.export(renamed)
    assert "pass modalities={'cam_ir': 'thermal'} to the import" in exported.lost[-1]
    with pytest.raises(RigError, match=r"cam_ir\.yaml: sensor 'cam_ir': .*modalities="):
        ros_format.import_(exported.files)
    imported = ros_format.import_(exported.files, modalities={"cam_ir": "thermal"})
    assert_same_rig(imported.rig, renamed)


def test_ros_reference_option_moves_the_rig_frame() -> None:
    rig = default_rig()
    imported = ros_format.import_(ros_format.export(rig).files, reference="ccd_left").rig
    assert imported.reference == "ccd_left"
    np.testing.assert_array_equal(imported["ccd_left"].T_rig_sensor, np.eye(4))
    for a in rig.names:
        np.testing.assert_allclose(imported.T(a, "tof"), rig.T(a, "tof"), atol=TOL)


def test_ros_without_poses_is_refused_unless_allowed() -> None:
    files = {k: v for k, v in ros_format.export(default_rig()).files.items() if k.endswith(".yaml")}
    with pytest.raises(RigError, match="allow_no_poses=True"):
        ros_format.import_(files)
    imported = ros_format.import_(files, allow_no_poses=True)
    assert imported.rig.reference == "tof"  # the first TOF camera
    for s in imported.rig.sensors.values():
        np.testing.assert_array_equal(s.T_rig_sensor, np.eye(4))
    text = "\n".join(imported.lost)
    assert "poses: no URDF among the files" in text
    assert "pose of ccd_left: ccd_left.yaml has none" in text
    assert "reference: not stated; the first TOF camera, tof, was chosen" in text


def test_real_camera_calibration_file() -> None:
    """ros-drivers/usb_cam's config/camera_info.yaml (BSD; tests/data/rig_formats/ros/README.md),
    written by ROS's camera_calibration: every number as the file has it."""
    text = ROS_SAMPLE.read_text()
    raw = yaml.safe_load(text)
    files = {"camera_info.yaml": text}
    with pytest.raises(RigError, match=r"camera_info\.yaml: sensor 'test_camera'.*modalities"):
        ros_format.import_(files, allow_no_poses=True)
    with pytest.raises(RigError, match="allow_no_poses"):
        ros_format.import_(files, modalities={"test_camera": "color"})
    imported = ros_format.import_(files, modalities={"test_camera": "color"}, allow_no_poses=True)
    rig = imported.rig
    assert rig.names == ["test_camera"] and rig.reference == "test_camera"
    cam = rig["test_camera"]
    assert cam.modality == "color"
    assert cam.image_size == (raw["image_width"], raw["image_height"]) == (640, 480)
    K = raw["camera_matrix"]["data"]
    i = cam.intrinsics
    assert (i.fx, i.fy, i.cx, i.cy) == (K[0], K[4], K[2], K[5])
    assert (i.fx, i.fy, i.cx, i.cy) == (438.783367, 437.302876, 305.593336, 243.738352)
    assert list(i.distortion) == raw["distortion_coefficients"]["data"]
    assert i.distortion == (-0.361976, 0.110510, 0.001014, 0.000505, 0.0)
    np.testing.assert_array_equal(cam.T_rig_sensor, np.eye(4))
    text_lost = "\n".join(imported.lost)
    assert (
        "rectification of test_camera: camera_info.yaml's rectification_matrix is not the identity"
        in text_lost
    )
    assert (
        "projection of test_camera: camera_info.yaml's projection_matrix is not [K | 0]"
        in text_lost
    )
    # Written again, it is a camera_info file with the same camera.
    again = yaml.safe_load(ros_format.export(rig).files["test_camera.yaml"])
    assert again["camera_matrix"]["data"] == K
    assert again["distortion_coefficients"]["data"] == raw["distortion_coefficients"]["data"]


def test_ros_missing_distortion_model_is_plumb_bob_as_in_ros() -> None:
    text = ros_format.export(default_rig()).files["tof.yaml"]
    text = "\n".join(line for line in text.splitlines() if not line.startswith("distortion_model"))
    imported = ros_format.import_({"tof.yaml": text}, allow_no_poses=True)
    assert imported.rig["tof"].intrinsics == default_rig()["tof"].intrinsics
    assert any("plumb_bob assumed" in line for line in imported.lost)


def _ros_case(key: str, value: object) -> dict[str, str]:
    files = dict(ros_format.export(default_rig()).files)
    data = yaml.safe_load(files["ccd_left.yaml"])
    if value is _DELETE:
        del data[key]
    else:
        data[key] = value
    files["ccd_left.yaml"] = yaml.safe_dump(data)
    return files


_DELETE = object()
_K = {"rows": 3, "cols": 3, "data": [1333.0, 0.0, 641.3, 0.0, 1331.2, 478.6, 0.0, 0.0, 1.0]}


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("camera_matrix", _DELETE, "camera_matrix: missing"),
        ("projection_matrix", _DELETE, "projection_matrix: missing"),
        ("image_width", "1280", "image_width: expected a positive integer"),
        ("image_height", True, "image_height: expected a positive integer"),
        ("image_width", 100_000, "megapixels"),
        ("camera_matrix", [1, 2, 3], "camera_matrix: expected a mapping"),
        ("camera_matrix", {**_K, "data": _K["data"][:8]}, r"rows x cols = 9 numbers, got 8"),
        ("camera_matrix", {**_K, "rows": 2, "data": _K["data"][:6]}, "expected 3 x 3, got 2 x 3"),
        ("camera_matrix", {**_K, "data": [*_K["data"][:8], "1"]}, r"data\[8\]: expected a number"),
        ("camera_matrix", {**_K, "data": [*_K["data"][:8], float("nan")]}, "finite"),
        ("camera_matrix", {**_K, "data": [1333.0, 5.0, *_K["data"][2:]]}, "skew"),
        (
            "camera_matrix",
            {**_K, "data": [-1.0, *_K["data"][1:]]},
            "focal lengths must be positive",
        ),
        ("distortion_model", "equidistant", "distortion_model: expected 'plumb_bob'"),
        (
            "distortion_coefficients",
            {"rows": 1, "cols": 8, "data": [0.1] * 8},
            "plumb_bob takes 4 or 5",
        ),
        ("distortion_coefficients", {"rows": 1, "cols": 3, "data": [0.1] * 3}, "got 3"),
        ("rectification_matrix", {"rows": 3, "cols": 4, "data": [0.0] * 12}, "expected 3 x 3"),
        ("camera_name", ["a", "b"], "camera_name: expected a name"),
    ],
)
def test_malformed_camera_info_names_the_file(key: str, value: object, match: str) -> None:
    with pytest.raises(RigError, match=match) as info:
        ros_format.import_(_ros_case(key, value))
    assert str(info.value).startswith("ccd_left.yaml: ")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"ccd_left.yaml": "camera_matrix: [1, 2"}, r"^ccd_left\.yaml: not valid YAML"),
        ({"ccd_left.yaml": "- 1\n- 2\n"}, r"^ccd_left\.yaml: expected a camera_info mapping"),
        ({"notes.txt": "hello"}, r"^notes\.txt: expected camera_info files"),
        ({"second.urdf": "<robot/>"}, r"^second\.urdf: a second URDF"),
        ({"trifuse_head.urdf": "<robot><link"}, r"^trifuse_head\.urdf: not valid XML"),
        (
            {"trifuse_head.urdf": '<robot name="r"><link name="rig"/></robot>'},
            r"^trifuse_head\.urdf: no joint places link 'tof_optical_frame'",
        ),
    ],
)
def test_malformed_ros_files(change: dict[str, str], match: str) -> None:
    files = {**ros_format.export(default_rig()).files, **change}
    with pytest.raises(RigError, match=match):
        ros_format.import_(files)


def test_ros_names_and_options() -> None:
    files = dict(ros_format.export(default_rig()).files)
    # Two files with one camera_name (camera_calibration's default "narrow_stereo"):
    # each sensor is named after its file.
    for name in ("thermal_left", "thermal_right"):
        files[f"{name}.yaml"] = files[f"{name}.yaml"].replace(
            f"camera_name: {name}", "camera_name: narrow_stereo"
        )
    imported = ros_format.import_(files, eyes=DEFAULT_EYES)
    assert imported.rig.names == default_rig().names
    assert any("shared by 2 files" in line for line in imported.lost)
    # A camera_name that is no sensor name: the file's stem.
    files["ccd_left.yaml"] = files["ccd_left.yaml"].replace(
        "camera_name: ccd_left", "camera_name: narrow_stereo/left"
    )
    assert ros_format.import_(files).rig.names == default_rig().names
    for options, match in (
        ({"eyes": {"left": ("ccd_left",)}}, "option eyes: eye 'left'"),
        ({"eyes": {"left": ("thermal_left", "ccd_left")}}, "option eyes: .*modality"),
        ({"modalities": {"nobody": "color"}}, "option modalities: no sensor 'nobody'"),
        ({"modalities": {"tof": "lidar"}}, "option modalities: sensor 'tof'"),
        ({"reference": "nobody"}, "option reference: no sensor 'nobody'"),
    ):
        with pytest.raises(RigError, match=match):
            ros_format.import_(files, **options)
    dup = {
        "a.yaml": files["tof.yaml"].replace("camera_name: tof", "camera_name: c"),
        "c.yaml": files["tof.yaml"].replace("camera_name: tof\n", ""),
    }
    with pytest.raises(RigError, match=r"c\.yaml: sensor 'c' is also described by a\.yaml"):
        ros_format.import_(dup, allow_no_poses=True, modalities={"c": "tof"})


# -- OpenCV ---------------------------------------------------------------------------------


def read_fs(text: str) -> cv2.FileStorage:
    fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    assert fs.isOpened()
    return fs


@pytest.mark.parametrize("make_rig", [default_rig, varied_rig], ids=["default", "varied"])
def test_opencv_files_read_by_filestorage(make_rig: Callable[[], Rig]) -> None:
    """cv2.FileStorage reads every number back, and R, T are stereoCalibrate's: OpenCV's
    projectPoints of reference-frame points with them lands where trifuse projects."""
    rig = make_rig()
    exported = opencv_format.export(rig)
    assert sorted(exported.files) == sorted(["rig.yml"] + [f"{n}.yml" for n in rig.names])
    index = read_fs(exported.files["rig.yml"])
    assert index.getNode("reference").string() == rig.reference
    seq = index.getNode("sensors")
    assert [seq.at(k).string() for k in range(seq.size())] == rig.names
    eyes = index.getNode("eyes")
    got_eyes = {
        eyes.at(k).getNode("name").string(): Eye(
            eyes.at(k).getNode("color").string(), eyes.at(k).getNode("thermal").string()
        )
        for k in range(eyes.size())
    }
    assert got_eyes == rig.eyes
    rng = np.random.default_rng(11)
    for name, sensor in rig.sensors.items():
        fs = read_fs(exported.files[f"{name}.yml"])
        assert fs.getNode("modality").string() == sensor.modality
        assert int(fs.getNode("image_width").real()) == sensor.width
        assert int(fs.getNode("image_height").real()) == sensor.height
        np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), sensor.intrinsics.K)
        D = fs.getNode("distortion_coefficients").mat()
        assert D.shape == (1, len(sensor.intrinsics.distortion))
        assert tuple(D.ravel()) == sensor.intrinsics.distortion
        R, T = fs.getNode("R").mat(), fs.getNode("T").mat()
        assert T.shape == (3, 1)
        T_sensor_ref = rig.T(name, rig.reference)
        np.testing.assert_allclose(R, T_sensor_ref[:3, :3], atol=1e-15)
        np.testing.assert_allclose(T.ravel(), T_sensor_ref[:3, 3], atol=1e-15)
        # Points in front of the sensor, expressed in the reference's frame.
        P_sensor = np.column_stack([rng.uniform(-0.3, 0.3, (20, 2)), rng.uniform(1.0, 3.0, 20)])
        P_ref = transform_points(invert(T_sensor_ref), P_sensor)
        rvec, _ = cv2.Rodrigues(R)
        uv_cv, _ = cv2.projectPoints(P_ref, rvec, T, fs.getNode("camera_matrix").mat(), D)
        np.testing.assert_allclose(
            uv_cv.reshape(-1, 2), sensor.intrinsics.project(P_sensor), atol=1e-6
        )


@pytest.mark.parametrize("make_rig", [default_rig, varied_rig], ids=["default", "varied"])
def test_opencv_round_trip(make_rig: Callable[[], Rig]) -> None:
    rig = make_rig()
    exported = export_rig(rig, "opencv")
    imported = import_rig(exported.files, "opencv")
    assert_same_rig(imported.rig, rig)
    assert imported.lost == []
    for name in rig.names:  # the distortion keeps its length
        assert imported.rig[name].intrinsics.distortion == rig[name].intrinsics.distortion
    if make_rig is varied_rig:
        assert sorted(exported.lost) == sorted(
            [
                "radiometry of thermal_rational: the OpenCV files have none",
                "range correction of tof: the OpenCV files have none",
                "uncertainty of tof: the OpenCV files have none",
            ]
        )
    else:
        assert exported.lost == []


def test_opencv_in_a_folder_and_without_the_index() -> None:
    rig = default_rig()
    files = {f"calib/{k}": v for k, v in opencv_format.export(rig).files.items()}
    assert_same_rig(opencv_format.import_(files).rig, rig)
    sensors_only = {k: v for k, v in files.items() if not k.endswith("rig.yml")}
    imported = opencv_format.import_(sensors_only, eyes=DEFAULT_EYES)
    assert_same_rig(imported.rig, rig)  # tof is the sensor with R = I, T = 0
    assert imported.lost == ["reference, sensor order and eyes: no rig.yml among the files"]


def test_opencv_calibration_sample_file() -> None:
    """A file as OpenCV's calibration sample writes it (no modality, no R and T, extra
    keys): read with the options that say what it lacks."""
    fs = cv2.FileStorage(
        "x.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML
    )
    fs.write("calibration_time", "Mon Jan  1 00:00:00 2024")
    fs.write("nr_of_frames", 13)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    K = np.array([[536.07, 0.0, 342.37], [0.0, 536.02, 235.54], [0.0, 0.0, 1.0]])
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([[-0.265], [-0.047], [0.0018], [-0.0003], [0.25]]))
    fs.write("avg_reprojection_error", 0.409)
    files = {"out_camera_data.xml": fs.releaseAndGetString()}
    with pytest.raises(
        RigError, match=r"out_camera_data\.xml: sensor 'out_camera_data': .*modalities"
    ):
        opencv_format.import_(files, allow_no_poses=True)
    with pytest.raises(RigError, match="allow_no_poses"):
        opencv_format.import_(files, modalities={"out_camera_data": "color"})
    imported = opencv_format.import_(
        files, modalities={"out_camera_data": "color"}, allow_no_poses=True
    )
    cam = imported.rig["out_camera_data"]
    np.testing.assert_array_equal(cam.intrinsics.K, K)
    assert cam.intrinsics.distortion == (-0.265, -0.047, 0.0018, -0.0003, 0.25)
    assert cam.image_size == (640, 480)


def _opencv_files(edit: Callable[[dict[str, str]], None]) -> dict[str, str]:
    files = dict(opencv_format.export(default_rig()).files)
    edit(files)
    return files


def _replace(path: str, old: str, new: str) -> Callable[[dict[str, str]], None]:
    def edit(files: dict[str, str]) -> None:
        assert old in files[path]
        files[path] = files[path].replace(old, new, 1)

    return edit


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (
            _replace("ccd_left.yml", "camera_matrix", "kamera_matrix"),
            r"^ccd_left\.yml: camera_matrix: missing",
        ),
        (
            _replace("ccd_left.yml", "image_width: 1280", "image_width: wide"),
            r"^ccd_left\.yml: image_width: expected a positive integer",
        ),
        (
            _replace(
                "ccd_left.yml", "   rows: 3\n   cols: 3", "   rows: 1000000\n   cols: 1000000"
            ),
            r"^ccd_left\.yml: camera_matrix: rows: expected an integer from 1 to 16",
        ),
        (
            _replace("ccd_left.yml", "   rows: 3\n   cols: 3", "   rows: 1\n   cols: 9"),
            r"^ccd_left\.yml: camera_matrix: expected 3 x 3, got 1 x 9",
        ),
        (
            _replace("ccd_left.yml", "data: [ 1333.", "data: [ 1333., 7."),
            r"^ccd_left\.yml: camera_matrix: not a valid matrix",
        ),
        (
            _replace("ccd_left.yml", "R: !!opencv-matrix", "R_unused: !!opencv-matrix"),
            r"^ccd_left\.yml: expected both R and T",
        ),
        (
            _replace("ccd_left.yml", "0.99980200689524357", "1.5"),
            r"^ccd_left\.yml: R: not a rotation",
        ),
        (
            _replace("ccd_left.yml", "modality: color", "modality: sonar"),
            r"^ccd_left\.yml: modality: expected one of",
        ),
        (
            _replace("ccd_left.yml", "%YAML 1.2\n---\n", "%YAML 1.2\n---\n[[[\n"),
            r"^ccd_left\.yml: not an OpenCV FileStorage file",
        ),
        (
            lambda f: f.update({"ccd_left.yml": ""}),
            r"^ccd_left\.yml: not an OpenCV FileStorage file \(empty",
        ),
        (
            lambda f: f.pop("ccd_left.yml"),
            r"^rig\.yml: sensor 'ccd_left': its file ccd_left\.yml is missing",
        ),
        (lambda f: f.update({"extra.yml": f["tof.yml"]}), r"^extra\.yml: not a sensor of rig\.yml"),
        (
            _replace("rig.yml", "reference: tof", "reference: nobody"),
            r"^rig\.yml: reference: 'nobody'",
        ),
        (
            _replace("rig.yml", "thermal: thermal_left", "thermal: ccd_right"),
            r"^rig\.yml: eyes: eyes\.left\.thermal: .*modality",
        ),
        (
            _replace("rig.yml", "   - ccd_left\n", "   - 12\n"),
            r"^rig\.yml: sensors\[1\]: expected a name, got the number 12",
        ),
    ],
)
def test_malformed_opencv_files_name_the_file(
    edit: Callable[[dict[str, str]], None], match: str
) -> None:
    with pytest.raises(RigError, match=match):
        opencv_format.import_(_opencv_files(edit))


def test_opencv_names_it_cannot_write() -> None:
    tof = default_rig()["tof"]
    for name, match in (("rig", "would overwrite rig.yml"), ("true", "would not read back")):
        other = Sensor(name, "color", tof.image_size, tof.intrinsics, np.eye(4))
        with pytest.raises(RigError, match=match):
            opencv_format.export(Rig({"tof": tof, name: other}, "tof"))


def test_exported_type() -> None:
    for fmt in ("ros", "opencv", "urdf"):
        assert isinstance(export_rig(default_rig(), fmt), Exported)
