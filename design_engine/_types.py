"""Array type aliases used across the engine (jaxtyping shapes, documented once)."""

from jaxtyping import Array, Bool, Float, Int

Scalar = Float[Array, ""]
DesignVector = Float[Array, " n_design"]  # flat design vector, mm (internal units)
Vertices = Float[Array, "n_blocks n_vertices 2"]  # per-block vertex offsets, mm
Points = Float[Array, "n_blocks 2"]  # one point per block, mm
BlockState = Float[Array, "n_blocks 3"]  # (u mm, v mm, theta rad) per block
FreeState = Float[Array, " n_free"]

__all__ = ["Array", "Bool", "Float", "Int", "Scalar", "DesignVector", "Vertices", "Points",
           "BlockState", "FreeState"]
