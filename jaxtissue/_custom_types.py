"""Array aliases with named axes (x along the strip, y across its thickness; `*batch`:
any leading axes, the same for every argument of one call)."""

from jaxtyping import Array, Float

Field = Float[Array, "*batch nx ny"]
"""A cell-centred field on the growth grid."""
FaceFieldX = Float[Array, "*batch nx+1 ny"]
"""A value on the faces normal to x, the two ends included."""
FaceFieldY = Float[Array, "*batch nx ny+1"]
"""A value on the faces normal to y, the two surfaces included."""
