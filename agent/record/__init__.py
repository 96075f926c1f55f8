"""Record and replay in MCAP: ``uma record``, ``uma play``, ``uma info``.

A recording is one MCAP file (the format of rosbag2 and Foxglove, written and read with the
``mcap`` package): one channel per data key with the exact msgpack bytes that were on the
wire, the agents' service snapshots and SRG summaries as they changed, and, for ROS 2
tools, the poses as ``tf2_msgs/msg/TFMessage`` on ``/tf`` and ``/tf_static``.

``layout`` names the channels; ``sink`` writes them (its own thread, bounded queue, counted
drops, a full disk stops it cleanly); ``recorder`` feeds it from Zenoh; ``reader`` reads a
file back, up to the damage if it is truncated; ``info`` and ``player`` are the other two
commands; ``ros`` encodes the ROS 2 channels.  Needs the ``record`` extra
(``pip install 'uma-tracking[record]'``).

Public, for tools that read a recording (``uma eval fusion --from``): :func:`read`, the
:class:`Recording` and :class:`Message` it returns, :mod:`agent.record.layout` (the
channels) and :func:`decode_statics` (the static edges recorded beside the data).
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["Message", "Recording", "decode_statics", "layout", "read"]

__getattr__ = lazy_attributes(__name__, {"Message": "agent.record.reader",
                                         "Recording": "agent.record.reader",
                                         "read": "agent.record.reader",
                                         "decode_statics": "agent.record.statics",
                                         "layout": "agent.record.layout"})
