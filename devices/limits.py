"""What every device port shares: the refusal of a request outside the lab's limits, and a
device's own failure."""


class LimitError(ValueError):
    """A request outside the configured safety limits (the message says which and why); raised
    by a port before any device is told to move."""


class DeviceError(RuntimeError):
    """A device that refused a command, stopped answering, or is not the one expected (the
    message, one line, names the device and the command); raised by a driver, which the
    drivers' own error types extend."""
