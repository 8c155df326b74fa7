"""The ``[ros2]`` section: the daemon also publishes each batch as a ROS 2
``sensor_msgs/msg/PointCloud2`` (docs/ros2.md), natively over rmw_zenoh or for
zenoh-bridge-ros2dds.

``topic`` left out means ``/wristscan/<cell.name>/cloud`` (:meth:`Ros2Config.topic_for`; a cell
name character a ROS name cannot hold becomes ``_``).
"""

from __future__ import annotations

import re
from typing import Annotated, Literal

from pydantic import Field, field_validator

from wristscan.daemon.config.values import Bool, Int, Str, StrictModel

__all__ = ["Ros2Config", "default_topic"]

_ROS_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")
_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_FRAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_./-]*$")


def default_topic(cell_name: str) -> str:
    """``/wristscan/<cell>/cloud`` with the characters a ROS name cannot hold made ``_``."""
    cell = re.sub(r"[^A-Za-z0-9_]", "_", cell_name)
    if not cell or cell[0].isdigit():
        cell = f"c{cell}"
    return f"/wristscan/{cell}/cloud"


class Ros2Config(StrictModel):
    enabled: Bool = False
    """Also publish each batch as ``sensor_msgs/msg/PointCloud2`` (extra ``ros2``)."""
    mode: Literal["rmw_zenoh", "bridge"] = "rmw_zenoh"
    """``rmw_zenoh``: the key, attachment and liveliness tokens of rmw_zenoh, so ROS 2 nodes on
    ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` see the topic; ``bridge``: key = topic name, CDR payload,
    for zenoh-bridge-ros2dds."""
    distro: Literal["humble", "jazzy", "kilted", "lyrical", "rolling"] = "jazzy"
    """The ROS 2 distribution of the subscribers: the type hash in the key (Humble has none)."""
    domain_id: Annotated[Int, Field(ge=0, le=232)] = 0
    topic: Str | None = None
    """Absolute ROS 2 topic name (default ``/wristscan/<cell.name>/cloud``)."""
    node_name: Str = "wristscan"
    namespace: Str = "/"
    base_frame: Str = "base"
    """``frame_id`` of clouds published in the robot base frame (the UR driver's ``base``)."""
    table_frame: Str = "table"
    part_frame: Str = "part"
    flange_frame: Str = "flange"
    sensor_frame: Str = "wristscan_sensor"
    tf_static: Bool = False
    """Publish the calibration in force as ``/tf_static`` (flange -> sensor), so RViz can draw
    the sensor frame (rmw_zenoh mode)."""

    @field_validator("topic", "namespace")
    @classmethod
    def _ros_name(cls, v: str | None) -> str | None:
        if v is None or v == "/":
            return v
        if not v.startswith("/") or not _ROS_NAME.match(v):
            raise ValueError(
                f"not an absolute ROS 2 name {v!r} (e.g. '/wristscan/cell1/cloud': "
                "'/'-separated letters, digits and '_', not starting with a digit)"
            )
        return v

    @field_validator("node_name")
    @classmethod
    def _node(cls, v: str) -> str:
        if not _NODE_NAME.match(v):
            raise ValueError(f"not a ROS 2 node name {v!r} (letters, digits, '_')")
        return v

    @field_validator("base_frame", "table_frame", "part_frame", "flange_frame", "sensor_frame")
    @classmethod
    def _frame(cls, v: str) -> str:
        if not _FRAME.match(v):
            raise ValueError(f"not a tf frame name {v!r}")
        return v

    def topic_for(self, cell_name: str) -> str:
        """The topic: as configured, else ``/wristscan/<cell>/cloud``."""
        return self.topic if self.topic is not None else default_topic(cell_name)

    def frame_id(self, frame: str) -> str:
        """The ROS frame name of a wristscan frame (``base``, ``table``, ``part``)."""
        return {"base": self.base_frame, "table": self.table_frame, "part": self.part_frame}.get(
            frame, frame
        )
