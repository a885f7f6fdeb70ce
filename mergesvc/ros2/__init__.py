"""ROS 2 without a bridge process: mergesvc's outputs as rmw_zenoh topics (docs/ros2.md).

The layer above fleet: `Ros2Publisher` publishes factors, relocalization answers, the merged map
and trajectories as ROS 2 messages in a Zenoh session; `Ros2Bridge` feeds it from a running
service (or its Zenoh keys). Needs the `ros2` extra (rosbags) at run time.
"""

from mergesvc.ros2.bridge import Ros2Bridge
from mergesvc.ros2.messages import DEFAULT_DISTRO, RosType, type_hash
from mergesvc.ros2.names import Qos, topic_key
from mergesvc.ros2.publisher import Ros2Publisher

__all__ = ["DEFAULT_DISTRO", "Qos", "Ros2Bridge", "Ros2Publisher", "RosType", "topic_key",
           "type_hash"]
