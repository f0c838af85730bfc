"""Live DIC tracker node: per-unit poses from the camera at a decimated preview rate.

Interfaces (node name `dic_tracker`):
- subscribes `image_topic` (sensor_msgs/Image mono8/mono16, default `/camera/image_raw`);
  the callback only hands the frame to `LivePreview` (newest-frame slot), so it never waits
  for tracking and the camera is never blocked;
- subscribes `/rig/design` (std_msgs/String JSON with `polygons_m`, latched) when
  `units_path` is empty; where the design (or the units file) carries its lattice
  (`lattice.ligament_length_m`), every pose is also checked against its bonded neighbours
  (`tracking.neighbours`);
- publishes `poses_topic` (metarig_msgs/UnitPose2DArray, default `/dic/poses`) at most
  `preview_rate_hz`: ids, x, y (reference centroid + displacement, m, sample frame), theta
  (rad, CCW), quality (ZNCC), lost (x, y, theta NaN); the stamp is the frame's;
- service `~/reset_reference` (std_srvs/Trigger): the next frame becomes the reference. It is
  offered only once the unit outlines are known and the tracking kernels are compiled
  (`LivePreview.warm_up`), so that `metarig rig --live-dic` waits for it before the capture:
  a cold numba cache otherwise left a short capture without a single live pose;
- `/camera/reference_image` (latched): when the camera has taken one (the unloaded sample), it
  is the reference and the next frame's units are searched for in it, so that poses are from the
  unloaded design even on a pre-compressed sample.
The first frame tracked is the reference configuration. Parameters: `DICNodeConfig`
(`ros_nodes.dic_params`); the tracking itself is `tracking.live.LivePreview`.
"""

import json

import numpy as np
from metarig_msgs.msg import UnitPose2DArray
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from metarig.polygon import area_centroids
from ros_nodes import convert, topics
from ros_nodes import topics as T
from ros_nodes.dic_params import DICNodeConfig
from ros_nodes.nodes._common import LATCHED, STREAM, run_node
from ros_nodes.nodes._params import TypedParams
from tracking.calibration import CalibrationError
from tracking.dic import DICTracker
from tracking.live import LivePreview
from tracking.units import UnitsError, design_bonds, load_unit_bonds, load_unit_polygons
from tracking.units import validate_polygons as _validate

NAME = "dic_tracker"


class DICTrackerNode(Node):
    """Adapter: camera frames -> `LivePreview` -> pose messages."""

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        self._params = TypedParams(self, DICNodeConfig)
        cfg = self._params.config
        try:
            self._calib = cfg.calibration()
        except CalibrationError as e:
            raise SystemExit(f"{NAME}: {e}") from None
        self._preview: LivePreview | None = None
        self._centroids = None
        self._warned_no_units = False
        self._reference: np.ndarray | None = None
        self.create_subscription(Image, topics.REFERENCE_IMAGE.name, self._on_reference, LATCHED)
        self._pub = self.create_publisher(UnitPose2DArray, cfg.poses_topic, STREAM)
        self.create_subscription(Image, cfg.image_topic, self._on_image, STREAM)
        self._reset_service = None  # offered once the tracker is warm: the rig waits for it
        if cfg.units_path:
            try:
                polys = load_unit_polygons(cfg.units_path)
                self._start(polys, load_unit_bonds(cfg.units_path, polys))
            except UnitsError as e:
                raise SystemExit(f"{NAME}: {e}") from None
        else:
            self.create_subscription(String, topics.RIG_DESIGN.name, self._on_design, LATCHED)
            self.get_logger().info(f"waiting for the unit outlines on {topics.RIG_DESIGN.name}")

    def _start(self, polygons: np.ndarray, bonds: np.ndarray | None = None) -> None:
        """Track these outlines; `bonds`: the lattice's ligaments, for the check of every pose
        against its neighbours (None: a design without a lattice, no such check)."""
        cfg = self._params.config
        if self._preview is not None:
            self._preview.close()
        tracker = DICTracker(polygons, self._calib, cfg.tracker, bonds)
        self._centroids = area_centroids(tracker.polygons_m)
        self._preview = LivePreview(tracker, cfg.preview_rate_hz, self._publish, cfg.threads)
        took = self._preview.warm_up()
        self._preview.start()
        if self._reset_service is None:
            self._reset_service = self.create_service(Trigger, T.DIC_RESET.name, self._on_reset)
            self.get_logger().info(f"tracker warm in {took:.1f} s: {T.DIC_RESET.name} offered")
        if self._reference is not None:
            self._preview.reset_reference(self._reference)
        self.get_logger().info(f"tracking {tracker.n_units} units at <= "
                               f"{cfg.preview_rate_hz:g} Hz on {cfg.poses_topic}")

    def _on_design(self, msg: String) -> None:
        try:
            design = json.loads(msg.data)
            polys = _validate(design["polygons_m"], where=topics.RIG_DESIGN.name)
            self._start(polys, design_bonds(design, polys, topics.RIG_DESIGN.name))
        except (ValueError, KeyError, TypeError) as e:
            self.get_logger().error(f"{topics.RIG_DESIGN.name} has no usable polygons_m: {e}")

    def _on_reference(self, msg) -> None:
        try:
            self._reference = np.array(convert.image_array(msg))
        except ValueError as e:
            self.get_logger().warning(f"reference image unusable: {e}")
            return
        if self._preview is not None:
            self._preview.reset_reference(self._reference)
        self.get_logger().info("reference image received: the next frame is searched in it")

    def _on_image(self, msg) -> None:
        if self._preview is None:
            if not self._warned_no_units:
                self.get_logger().warning("frames arrive but no unit outlines yet: dropped")
                self._warned_no_units = True
            return
        try:
            frame = np.array(convert.image_array(msg))  # own copy: the message may be reused
        except ValueError as e:
            self.get_logger().warning(f"frame skipped: {e}", throttle_duration_sec=5.0)
            return
        self._preview.offer(convert.to_ns(msg.header.stamp), frame)

    def _publish(self, stamp_ns: int, poses) -> None:
        self._pub.publish(convert.unit_poses(stamp_ns, poses.q, self._centroids, poses.quality,
                                             poses.lost, sigma=poses.sigma))

    def _on_reset(self, _req, res):
        if self._preview is None:
            res.success, res.message = False, "no unit outlines yet"
        else:
            self._preview.reset_reference()
            res.success, res.message = True, "the next frame becomes the reference"
        return res

    def close(self) -> None:
        if self._preview is not None:
            self._preview.close()


def main(args=None) -> int:
    """Console entry point (`metarig-dic`)."""
    return run_node(DICTrackerNode, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
