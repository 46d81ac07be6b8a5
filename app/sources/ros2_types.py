"""The DDS types of the ROS 2 image messages as Cyclone DDS's Python binding declares them
(``IdlStruct`` with ROS 2's type names), for topics and readers to match a ROS 2 node's
(issue 36). Only their names and layout matter: samples are (de)serialised by
:mod:`app.sources.ros2_cdr`. Imports cyclonedds (the ``[ros2]`` extra): import this module
only where it is needed. (No ``from __future__ import annotations``: the binding resolves
the field types from their annotations.)"""

from dataclasses import dataclass

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float64, int32, sequence, uint8, uint32

from trifuse.app.sources.ros2_cdr import CAMERA_INFO, COMPRESSED, IMAGE, TF_MESSAGE, TYPE_NAMES


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Image(IdlStruct, typename=TYPE_NAMES[IMAGE]):
    header: Header
    height: uint32
    width: uint32
    encoding: str
    is_bigendian: uint8
    step: uint32
    data: sequence[uint8]


@dataclass
class CompressedImage(IdlStruct, typename=TYPE_NAMES[COMPRESSED]):
    header: Header
    format: str
    data: sequence[uint8]


IDL_TYPES: dict[str, type] = {IMAGE: Image, COMPRESSED: CompressedImage}
"""ROS 2 message type -> its IdlStruct."""


@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: uint32
    y_offset: uint32
    height: uint32
    width: uint32
    do_rectify: bool


@dataclass
class CameraInfo(IdlStruct, typename=TYPE_NAMES[CAMERA_INFO]):
    header: Header
    height: uint32
    width: uint32
    distortion_model: str
    d: sequence[float64]
    k: array[float64, 9]
    r: array[float64, 9]
    p: array[float64, 12]
    binning_x: uint32
    binning_y: uint32
    roi: RegionOfInterest


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename=TYPE_NAMES[TF_MESSAGE]):
    transforms: sequence[TransformStamped]


IDL_TYPES.update({CAMERA_INFO: CameraInfo, TF_MESSAGE: TFMessage})
