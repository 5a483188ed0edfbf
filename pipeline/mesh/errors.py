"""The one error type of the mesh layer (its own module so loaders and texture checks share it)."""


class MeshError(ValueError):
    """A mesh that cannot be used: empty, zero-area, non-finite, too large, unreadable."""
