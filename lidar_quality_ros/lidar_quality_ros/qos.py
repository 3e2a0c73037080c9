"""QoS profiles of the suite: sensor-data QoS on inputs, reliable QoS on outputs."""
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

#: Inputs (clouds, detections): best effort, keep last 5. A best-effort subscription
#: matches both best-effort and reliable publishers.
SENSOR_QOS: QoSProfile = qos_profile_sensor_data


def output_qos(depth: int = 10) -> QoSProfile:
    """Reliable, volatile, keep-last QoS for annotated outputs."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
