"""The linear stage pair that pre-compresses the sample: its port (`devices.stage.port`); the
simulated stages are `hardware_sim.stage.SimulatedStages`."""
