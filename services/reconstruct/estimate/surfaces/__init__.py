"""Every surface of a sweep: regions of constant depth, classified as planes, concave corners or convex edges."""

from lelsonar.reconstruct.estimate.surfaces.extract import (
    METHOD,
    UNSETTLED,
    Feature,
    Surface,
    SurfaceOptions,
    SurfaceSet,
    extract_surfaces,
)

__all__ = ["METHOD", "UNSETTLED", "Feature", "Surface", "SurfaceOptions", "SurfaceSet", "extract_surfaces"]
