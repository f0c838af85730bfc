"""comparison: experiment against simulation (spec 12.4), no ROS.

From a measured `Trajectory` (tracked poses) and the measured input, run the engine on exactly
that input, align the two in time and compute velocity and kinetic-energy fields and errors.
"""
