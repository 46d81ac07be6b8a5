"""The DDS types of the ROS 2 image messages as Cyclone DDS's Python binding declares them
(``IdlStruct`` with ROS 2's type names), for topics and readers to match a ROS 2 node's
(issue 36). Only their names and layout matter: samples are (de)serialised by
:mod:`app.sources.ros2_cdr`. Imports cyclonedds (the ``[ros2]`` extra): import this module
only where it is needed. (No ``from __future__ import annotations``: the binding resolves
the field types from their annotations.)"""

from dataclasses import dataclass

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import int32, sequence, uint8, uint32

from trifuse.app.sources.ros2_cdr import COMPRESSED, IMAGE, TYPE_NAMES


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
