"""Array aliases with named axes (x along the strip, y across its thickness)."""

from jaxtyping import Array, Float

Field = Float[Array, "nx ny"]
"""A cell-centred field on the growth grid."""
FaceFieldX = Float[Array, "nx+1 ny"]
"""A value on the faces normal to x, the two ends included."""
FaceFieldY = Float[Array, "nx ny+1"]
"""A value on the faces normal to y, the two surfaces included."""
Profile = Float[Array, "ny"]
"""A transmural profile at one section."""
Scalar = Float[Array, ""]
