"""Poses as ROS 2 ``tf2_msgs/msg/TFMessage`` in CDR, for ``ros2 bag``, Foxglove and
``rosbags``.

Serialisation and the message definition (the ``ros2msg`` schema text, dependencies
concatenated) come from the ``rosbags`` type store of ROS 2 Humble, the way the ``rosbags``
rosbag2 writer registers them; nothing here encodes CDR by hand.  uma's edge ``A -> B`` is the
pose of B in A's coordinates, which is ROS's transform with ``header.frame_id`` A and
``child_frame_id`` B; quaternions are x, y, z, w in both.
"""

from __future__ import annotations

from typing import Any

TF_TYPE = "tf2_msgs/msg/TFMessage"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"


class TfEncoder:
    """Builds TFMessage CDR bytes; one per recording (the type store is built once)."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_HUMBLE)
        types = self.store.types
        self._tf = types[TF_TYPE]
        self._stamped = types["geometry_msgs/msg/TransformStamped"]
        self._header = types["std_msgs/msg/Header"]
        self._time = types["builtin_interfaces/msg/Time"]
        self._transform = types["geometry_msgs/msg/Transform"]
        self._vector = types["geometry_msgs/msg/Vector3"]
        self._quat = types["geometry_msgs/msg/Quaternion"]

    def schema(self) -> bytes:
        """The ``ros2msg`` definition of TFMessage with its dependencies."""
        text, _ = self.store.generate_msgdef(TF_TYPE, ros_version=2)
        return text.encode()

    def encode(self, parent: str, child: str, t_ns: int, position: Any,
               quaternion: Any) -> bytes:
        """One transform as a TFMessage."""
        x, y, z = (float(v) for v in position)
        qx, qy, qz, qw = (float(v) for v in quaternion)
        stamp = self._time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        msg = self._tf(transforms=[self._stamped(
            header=self._header(stamp=stamp, frame_id=parent), child_frame_id=child,
            transform=self._transform(translation=self._vector(x=x, y=y, z=z),
                                      rotation=self._quat(x=qx, y=qy, z=qz, w=qw)))])
        return bytes(self.store.serialize_cdr(msg, TF_TYPE))
