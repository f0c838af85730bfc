"""What every device port shares: the refusal of a request outside the lab's limits."""


class LimitError(ValueError):
    """A request outside the configured safety limits (the message says which and why); raised
    by a port before any device is told to move."""
