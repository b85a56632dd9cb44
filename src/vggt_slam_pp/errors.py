"""The one exception family of VGGT-SLAM++.

Every error the library raises on purpose derives from :class:`VggtSlamError`; each module has its own
subclass so callers can catch one stage's failures. The CLI turns any of them into a one-line message
and a non-zero exit code. Messages name the offending thing (a path, a line, a shape) and, where it
helps, what to do about it.
"""

from __future__ import annotations


class VggtSlamError(Exception):
    """Base class of every error raised on purpose by VGGT-SLAM++."""


class GeometryError(VggtSlamError):
    """Bad geometric input: wrong shapes, degenerate point sets, non-finite values."""


class InputError(VggtSlamError):
    """A frame source cannot be opened or read: missing path, empty folder, unreadable image."""


class TrajectoryError(VggtSlamError):
    """A trajectory file is missing, malformed, or cannot be associated with another."""


class EvaluationError(VggtSlamError):
    """Trajectory evaluation cannot be carried out (no overlap in time, too few poses)."""


class SyntheticError(VggtSlamError):
    """Bad parameters for a synthetic world, trajectory or rendering."""


class ModelError(VggtSlamError):
    """A network cannot be built or run: bad configuration, wrong input shape, non-finite output."""


class WeightsError(ModelError):
    """Weights cannot be found, downloaded, read or matched to a model (missing/unexpected keys)."""


class FrontendError(VggtSlamError):
    """The front-end cannot run: too few frames, a backbone failure it cannot degrade around, bad config."""


class DemError(VggtSlamError):
    """A DEM cannot be built: too few points for a ground plane, an empty layer, bad grid parameters."""


class RetrievalError(VggtSlamError):
    """Descriptors or the tile index cannot be used: wrong dimension, an index from another configuration."""


class BackendError(VggtSlamError):
    """The back-end failed: a bad pose-graph edge, a solver failure, or the worker process died."""
