"""tracking: digital image correlation (DIC) of rigid units in camera frames; no ROS, no simulator.
"""
