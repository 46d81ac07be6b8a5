"""The rig's poses as a URDF fragment (issue 21; docs/FORMATS.md, "Rig formats").

A URDF describes a robot as links joined by joints; ``robot_state_publisher`` turns its
fixed joints into ``/tf_static``. :func:`export` writes one ``<robot>`` with

* one root link for the rig frame, ``<prefix>rig`` (or the ``base_link`` option). The rig
  frame *is* the reference sensor's optical frame (docs/CONVENTIONS.md), so the reference
  sensor's joint is the identity; a robot attaches the head by a joint from its own link to
  this root;
* one link per sensor, ``<prefix><sensor>_optical_frame`` (ROS's name for a camera's
  optical frame, the ``frame_id`` its driver should stamp on images and ``camera_info``;
  ``link_suffix=""`` names it ``<prefix><sensor>`` instead, the ``frame_id`` of trifuse's
  own recordings and of their ``/tf``, docs/FORMATS.md);
* one ``<joint type="fixed">`` per sensor, named after its link plus ``_joint``, from
  the root link to the sensor's link, in the rig's sensor order.

Frames: trifuse's sensor frames already follow ROS's optical-frame convention (REP 103:
x right, y down, z forward), so no axis swap is needed; metres and radians throughout. A
joint's ``<origin xyz="x y z" rpy="roll pitch yaw"/>`` is the child's pose in the parent:
``T_parent_child`` = ``[R | xyz]`` with URDF's fixed-axis roll-pitch-yaw,
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; for the rig, ``T_parent_child`` = ``T_rig_sensor``.
Numbers are written with ``repr`` (the shortest text that reads back exactly), so the poses
read back to about 1e-16 (the sines and cosines of the angles), at any pitch, gimbal lock
included.

A URDF holds only poses: intrinsics, distortion, image sizes, modality, radiometry, range
correction, uncertainty and the eyes are listed in ``Exported.lost``. There is no URDF
import on its own (``calib.rig_formats.IMPORT_FORMATS``); :func:`joints_from_urdf`,
:func:`poses_from_urdf` and :func:`relative_pose` read the poses back for the ROS import
(``calib.rig_formats.ros_format``).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig
from trifuse.calib.rig_formats import Exported
from trifuse.calib.rig_formats.common import extras_lost
from trifuse.calib.transforms import (
    invert,
    make_T,
    rigidity_problem,
    rotation_from_rpy,
    rpy_from_rotation,
)

OPTICAL_SUFFIX = "_optical_frame"
"""A sensor's link is ``<prefix><sensor>_optical_frame`` by default (``link_suffix``)."""
JOINT_SUFFIX = "_joint"
"""A sensor's joint is its link's name followed by ``_joint``."""
DEFAULT_ROOT = "rig"
"""The root link (the rig frame) is ``<prefix>rig`` unless ``base_link`` names it."""
MAX_URDF_CHARS = 10_000_000
"""Longest URDF text read (10 MB; a head's fragment is a few kilobytes)."""

_LINK_NAME_RE = re.compile(r"[A-Za-z0-9_./-]+")
"""Names written into the URDF: a tf frame id without spaces (``/`` allowed inside)."""


def sensor_link(sensor: str, prefix: str = "", suffix: str = OPTICAL_SUFFIX) -> str:
    """The URDF link (and tf frame) of ``sensor``: ``<prefix><sensor><suffix>``, by default
    ``<sensor>_optical_frame``."""
    return f"{prefix}{sensor}{suffix}"


# -- export ---------------------------------------------------------------------------------


def _check_name(value: str, option: str) -> str:
    """``value`` if it is a link name (:data:`_LINK_NAME_RE`), else RigError naming ``option``."""
    if not isinstance(value, str) or not _LINK_NAME_RE.fullmatch(value):
        raise RigError(
            f"URDF option {option}: expected letters, digits, '_', '.', '/' or '-', got {value!r}"
        )
    return value


def _numbers(values: Sequence[float]) -> str:
    """Space-separated ``repr`` of floats: the shortest text that reads back exactly."""
    return " ".join(repr(float(v) + 0.0) for v in values)  # + 0.0: no "-0.0"


def export(
    rig: Rig,
    *,
    robot_name: str = "trifuse_head",
    base_link: str | None = None,
    prefix: str = "",
    link_suffix: str = OPTICAL_SUFFIX,
) -> Exported:
    """The rig's poses as a URDF fragment, ``<robot_name>.urdf`` (see the module docstring).

    Args:
        rig: the rig.
        robot_name: the ``<robot name>``, also the file's stem.
        base_link: name of the root link (the rig frame, i.e. the reference sensor's
            optical frame); default ``<prefix>rig``.
        prefix: put before every link and joint name (e.g. ``head/`` for a second head).
        link_suffix: put after the sensor's name in its link's name: ``_optical_frame``
            (ROS's convention) or ``""`` (the frame ids of trifuse's recordings).

    Returns:
        ``files`` = ``{"<robot_name>.urdf": text}``; ``lost`` = what a URDF cannot hold.

    Raises:
        RigError: a name that is not a valid link name, or a pose that is not rigid.
    """
    _check_name(robot_name, "robot_name")
    if prefix:
        _check_name(prefix, "prefix")
    if link_suffix:
        _check_name(link_suffix, "link_suffix")
    root = _check_name(base_link, "base_link") if base_link is not None else prefix + DEFAULT_ROOT
    links = {name: sensor_link(name, prefix, link_suffix) for name in rig.sensors}
    clash = [n for n, link in links.items() if link == root]
    if clash:
        raise RigError(f"URDF: sensor {clash[0]!r}'s link has the root link's name {root!r}")

    robot = ET.Element("robot", {"name": robot_name})
    robot.append(
        ET.Comment(
            f" trifuse rig: the root link {root!r} is the rig frame, the optical frame of "
            f"the reference sensor {rig.reference!r}. The sensors' links are OpenCV/ROS "
            "optical frames (x right, y down, z forward); origins are metres and URDF "
            "roll-pitch-yaw radians (R = Rz(yaw) Ry(pitch) Rx(roll)). "
        )
    )
    ET.SubElement(robot, "link", {"name": root})
    for link in links.values():
        ET.SubElement(robot, "link", {"name": link})
    for name in rig.sensors:
        T = rig.T(rig.reference, name) if name != rig.reference else np.eye(4)
        problem = rigidity_problem(T)
        if problem is not None:
            raise RigError(f"sensor {name!r}: field 'T_rig_sensor': not rigid: {problem}")
        joint = ET.SubElement(robot, "joint", {"name": links[name] + JOINT_SUFFIX, "type": "fixed"})
        ET.SubElement(joint, "parent", {"link": root})
        ET.SubElement(joint, "child", {"link": links[name]})
        ET.SubElement(
            joint,
            "origin",
            {"xyz": _numbers(T[:3, 3]), "rpy": _numbers(rpy_from_rotation(T[:3, :3]))},
        )
    ET.indent(robot, space="  ")
    text = '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"
    return Exported(files={f"{robot_name}.urdf": text}, lost=pose_only_losses(rig, "a URDF"))


def pose_only_losses(rig: Rig, what: str) -> list[str]:
    """What a file holding only poses (``what``, e.g. "a URDF") loses of ``rig``."""
    names = ", ".join(rig.sensors)
    lost = [
        f"intrinsics, distortion and image size of every sensor ({names}): {what} holds only poses",
        f"modality of every sensor ({names}): {what} holds only poses",
    ]
    lost += extras_lost(rig, f"{what} holds only poses")
    if rig.eyes:
        lost.append(f"eyes ({', '.join(rig.eyes)}): {what} holds only poses")
    return lost


# -- reading ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class UrdfJoint:
    """One joint of a URDF.

    Attributes:
        name: the joint's name.
        joint_type: ``fixed``, ``revolute``, ``continuous``, ``prismatic``, ``floating``
            or ``planar``.
        parent: the parent link.
        child: the child link.
        T_parent_child: (4, 4) pose of the child link in the parent link at joint
            position 0 (the ``<origin>``), metres.
    """

    name: str
    joint_type: str
    parent: str
    child: str
    T_parent_child: np.ndarray


_JOINT_TYPES = ("fixed", "revolute", "continuous", "prismatic", "floating", "planar")


def _triple(element: ET.Element, attr: str, where: str) -> tuple[float, float, float]:
    """Three finite numbers of attribute ``attr`` (default ``0 0 0``), else RigError."""
    raw = element.get(attr, "0 0 0")
    parts = raw.split()
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise RigError(f"{where}: origin {attr}: expected three finite numbers, got {raw!r}")
    return values  # type: ignore[return-value]


def is_urdf(text: str) -> bool:
    """Whether ``text`` is an XML document whose root element is ``<robot>`` (within the
    limits :func:`joints_from_urdf` keeps)."""
    if len(text) > MAX_URDF_CHARS or "<!DOCTYPE" in text or "<!ENTITY" in text:
        return False
    try:
        return ET.fromstring(text).tag == "robot"
    except ET.ParseError:
        return False


def joints_from_urdf(text: str, source: str = "URDF") -> list[UrdfJoint]:
    """The joints of a URDF document, in file order.

    Args:
        text: the URDF (XML) text.
        source: the file's name, for error messages.

    Raises:
        RigError (naming ``source`` and the joint): not XML, no ``<robot>`` root, a joint
        without name, type, parent or child, an unknown type, an origin that is not three
        finite numbers each, or a link that is the child of two joints.
    """
    if len(text) > MAX_URDF_CHARS:
        raise RigError(f"{source}: {len(text)} characters; expected at most {MAX_URDF_CHARS}")
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        raise RigError(f"{source}: document type declarations (<!DOCTYPE, <!ENTITY) are refused")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise RigError(f"{source}: not valid XML: {exc}") from None
    if root.tag != "robot":
        raise RigError(f"{source}: expected a <robot> root element, got <{root.tag}>")
    joints: list[UrdfJoint] = []
    children: set[str] = set()
    for i, element in enumerate(root.iter("joint")):
        name = element.get("name")
        where = f"{source}: joint {name!r}" if name else f"{source}: joint #{i + 1}"
        if not name:
            raise RigError(f"{where}: missing attribute 'name'")
        joint_type = element.get("type")
        if joint_type not in _JOINT_TYPES:
            raise RigError(
                f"{where}: type: expected one of {list(_JOINT_TYPES)}, got {joint_type!r}"
            )
        ends = {}
        for tag in ("parent", "child"):
            found = element.find(tag)
            link = found.get("link") if found is not None else None
            if not link:
                raise RigError(f"{where}: missing <{tag} link=...>")
            ends[tag] = link
        if ends["child"] in children:
            raise RigError(f"{where}: link {ends['child']!r} is the child of two joints")
        children.add(ends["child"])
        origin = element.find("origin")
        xyz, rpy = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        if origin is not None:
            xyz, rpy = _triple(origin, "xyz", where), _triple(origin, "rpy", where)
        T = make_T(rotation_from_rpy(*rpy), xyz)
        joints.append(UrdfJoint(name, joint_type, ends["parent"], ends["child"], T))
    return joints


def poses_from_urdf(text: str, source: str = "URDF") -> dict[str, np.ndarray]:
    """Child link -> ``T_parent_child`` (4, 4), metres, of every joint of a URDF (at joint
    position 0 for joints that move). RigError as :func:`joints_from_urdf`."""
    return {j.child: j.T_parent_child for j in joints_from_urdf(text, source)}


def common_frame_poses(
    joints: Sequence[UrdfJoint], links: Sequence[str], source: str = "URDF"
) -> tuple[str, dict[str, np.ndarray]]:
    """The poses of ``links`` in the frame of their lowest common ancestor link.

    Returns:
        (the ancestor's name, link -> ``T_ancestor_link`` (4, 4), metres).

    Raises:
        RigError (naming ``source``): no links, a link that no joint or ``<link>`` names
        (checked by the caller), links in different trees, or a joint that moves between
        the ancestor and a link.
    """
    if not links:
        raise RigError(f"{source}: no links to place")
    by_child = {j.child: j for j in joints}
    chains = [_chain(by_child, link, source) for link in links]
    ancestor = chains[0][0].parent if chains[0] else links[0]
    depth = 0
    while all(len(c) > depth for c in chains) and all(c[depth] is chains[0][depth] for c in chains):
        depth += 1
    if depth:
        ancestor = chains[0][depth - 1].child
    return ancestor, {link: relative_pose(joints, ancestor, link, source) for link in links}


def _chain(by_child: dict[str, UrdfJoint], link: str, source: str) -> list[UrdfJoint]:
    """The joints from the root of ``link``'s tree down to ``link`` (root first)."""
    chain: list[UrdfJoint] = []
    seen = {link}
    while link in by_child:
        joint = by_child[link]
        chain.append(joint)
        link = joint.parent
        if link in seen:
            raise RigError(f"{source}: the joints form a loop through link {link!r}")
        seen.add(link)
    return chain[::-1]


def relative_pose(
    joints: Sequence[UrdfJoint], dst: str, src: str, source: str = "URDF"
) -> np.ndarray:
    """``T_dst_src`` (4, 4) between two links of a URDF's tree, through their common
    ancestor.

    Raises:
        RigError (naming ``source``): the links are in different trees, or a joint that
        moves lies between them (their relative pose would depend on the joint's state).
    """
    by_child = {j.child: j for j in joints}
    chains = {link: _chain(by_child, link, source) for link in (dst, src)}
    roots = {link: (c[0].parent if c else link) for link, c in chains.items()}
    if roots[dst] != roots[src]:
        raise RigError(
            f"{source}: links {dst!r} and {src!r} are not connected (their roots are "
            f"{roots[dst]!r} and {roots[src]!r})"
        )
    common = 0
    a, b = chains[dst], chains[src]
    while common < min(len(a), len(b)) and a[common] is b[common]:
        common += 1
    poses = {}
    for link, chain in ((dst, a), (src, b)):
        T = np.eye(4)
        for joint in chain[common:]:
            if joint.joint_type != "fixed":
                raise RigError(
                    f"{source}: joint {joint.name!r} between links {dst!r} and {src!r} is "
                    f"{joint.joint_type}, not fixed: their relative pose is not constant"
                )
            T = T @ joint.T_parent_child
        poses[link] = T
    return invert(poses[dst]) @ poses[src]
