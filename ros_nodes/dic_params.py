"""Parameters of the live DIC tracker node (pure, no rclpy): a typed config over `tracking`."""

from dataclasses import dataclass

from metarig.fields import param
from ros_nodes import topics
from tracking.calibration import Calibration, calibration_from_dict, load_calibration
from tracking.dic import DICConfig


# the preview tracks a decimated stream (`preview_rate_hz` of a 1000 fps camera): units move
# further between the frames it sees than between a camera's frames, so its search windows are
# twice the offline tracker's, and of the neighbours' check only the ligaments' departure from
# their rest vectors applies (their acceleration is bounded between a camera's frames: at the
# largest value the bound is no test)
LIVE_TRACKER = DICConfig(search_radius_px=24, lost_search_radius_px=48, neighbour_px=1000.0)


@dataclass(frozen=True, slots=True)
class DICNodeConfig:
    """Parameters of the live DIC tracker node (ROS parameters of the same names)."""

    image_topic: str = param(topics.IMAGE.name, "camera frames (sensor_msgs/Image mono8/16)")
    poses_topic: str = param(topics.POSES.name, "per-unit poses out (metarig_msgs/UnitPose2DArray)")
    units_path: str = param("", "JSON with polygons_m; empty: the latched /rig/design topic")
    calibration_path: str = param("", "calibration JSON; empty: fps, m_per_px, origin_* below")
    fps: float = param(1000.0, "camera frame rate (without calibration_path), Hz", 0.1, 1e6)
    m_per_px: float = param(6.0e-4, "image scale (without calibration_path), m/px", 1e-7, 1.0)
    origin_col: float = param(0.0, "pixel column of the sample origin (without calibration_path)")
    origin_row: float = param(0.0, "pixel row of the sample origin (without calibration_path)")
    y_up: bool = param(True, "sample y points up the image (without calibration_path)")
    preview_rate_hz: float = param(
        20.0, "most pose messages per second (decimated preview)", 0.1, 10000.0
    )
    threads: int = param(1, "numba threads for tracking (leave cores to the camera)", 1, 256)
    tracker: DICConfig = param(lambda: LIVE_TRACKER, "tracker settings (tracking.dic.DICConfig)")

    def calibration(self) -> Calibration:
        """The calibration from `calibration_path`, or from the inline parameters."""
        if self.calibration_path:
            return load_calibration(self.calibration_path)
        return calibration_from_dict(
            {
                "fps": self.fps,
                "m_per_px": self.m_per_px,
                "origin_px": [self.origin_col, self.origin_row],
                "y_up": self.y_up,
            },
            where="node parameters",
        )
