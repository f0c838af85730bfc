"""Lab devices behind small ports: what the rig needs of a real device, and drivers that
implement it through the vendors' packages.

This package knows no ROS, no simulator and no JAX (numpy and the vendor packages only; it
may import the `metarig` base). Every command is checked against the device's limits in the
port before a driver touches the device.

    devices.limits   `LimitError`, the refusal every port raises before a device moves
    devices.shaker   the shaker port (`ShakerDrive`, `prepare`) and its waveforms and limits;
                     the simulated shaker (`hardware_sim.shaker.SimulatedShaker`) implements it
    devices.stage    the stage-pair port (`StagePair`, `StageLimits`, `check_strain`); the
                     simulated stages (`hardware_sim.stage.SimulatedStages`) implement it
    devices.camera   the camera port (`Camera`, `CameraSettings`, `Frame`, limits, frame-loss
                     counting, device-clock mapping) and its drivers: Basler pylon (pypylon)
                     and GenICam GenTL producers (harvesters)
    devices.lab      the lab file (TOML): drivers, addresses, calibration, limits, ROS domain
    devices.connect  opens the real devices a lab file names, checked to be those
    devices.probe    what this machine can see (cameras, VISA instruments, serial ports)
    devices.labcheck a lab file checked against the devices, nothing moved
    devices.cli      the `metarig devices` command
"""
