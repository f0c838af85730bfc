"""The shaker: waveforms checked against the limits (`devices.shaker.waveform`) and the port a
shaker drive implements (`devices.shaker.port`); the simulated shaker is
`hardware_sim.shaker.SimulatedShaker`."""
