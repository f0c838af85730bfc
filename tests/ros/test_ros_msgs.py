"""The project's interface package `metarig_msgs`: built by the install step, usable over DDS."""

import numpy as np
from rostools import spin_until, wait_matched


def test_build_is_idempotent_and_installed():
    from ros_nodes.interfaces import build

    dest = build.build()  # up to date: only checks the import
    assert (dest / "msg" / "__init__.py").exists()
    assert build.dependencies(build.interface_files()) == ["builtin_interfaces", "service_msgs",
                                                            "std_msgs"]


def test_unit_pose_array_round_trip_over_dds(ros_context):
    import rclpy
    from metarig_msgs.msg import UnitPose2DArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    a = rclpy.create_node("pose_pub", context=ros_context)
    b = rclpy.create_node("pose_sub", context=ros_context)
    got = []
    b.create_subscription(UnitPose2DArray, "poses", got.append, qos)
    pub = a.create_publisher(UnitPose2DArray, "poses", qos)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(a)
    ex.add_node(b)
    wait_matched(pub, ex)
    n = 384
    m = UnitPose2DArray()
    m.header.frame_id = "sample"
    m.ids = np.arange(n, dtype=np.uint32)
    m.x = np.linspace(0, 0.3, n)
    m.y = np.linspace(0, 0.2, n)
    m.theta = np.full(n, 0.01)
    m.quality = np.ones(n, np.float32)
    m.lost = [i % 7 == 0 for i in range(n)]
    pub.publish(m)
    spin_until(ex, lambda: got, 30.0, "the pose message")
    r = got[0]
    np.testing.assert_array_equal(np.asarray(r.ids), np.arange(n))
    np.testing.assert_allclose(np.asarray(r.x), m.x)
    assert list(r.lost) == m.lost and r.header.frame_id == "sample"
    ex.shutdown()
    a.destroy_node()
    b.destroy_node()


def test_services_exist():
    from metarig_msgs.srv import FirePulse, SetStrain

    assert FirePulse.Request().amplitude_m == 0.0
    assert SetStrain.Response().accepted is False
