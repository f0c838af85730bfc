"""Solving a scene in time: the integrators (diffrax, fixed and implicit steps), the one
solver policy (`policy`) and the runs of a scene (`run`)."""
