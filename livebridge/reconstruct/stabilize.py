"""Head stabilisation: the head pose from the rigid head markers.

The head frame is the face model's frame; removing ``head2world`` from the markers leaves what the face
did. The fit is :func:`livebridge.geometry.transforms.umeyama` without scale (Kabsch).
"""

from __future__ import annotations

import numpy as np

from livebridge.geometry.transforms import umeyama


def head_pose(reference_model: np.ndarray, points_world: np.ndarray, model_scale: float = 1.0,
              weights: np.ndarray | None = None) -> np.ndarray:
    """Head pose ``head2world`` from rigid head markers (Kabsch, scale fixed).

    ``head2world`` maps model coordinates into the capture world; it is rigid when capture and model
    share a scale, otherwise it carries the fixed ``model_scale`` (world mm per model mm) found by the
    coordinate alignment.

    Parameters
    ----------
    reference_model : ndarray, shape (n_head, 3)
        Head-marker positions in the model (head) frame.
    points_world : ndarray, shape (n_head, 3)
        Their positions this frame in the world frame; NaN where not seen.
    model_scale : float
        World millimetres per model millimetre.
    weights : ndarray, shape (n_head,), optional
        Non-negative weight per marker (default: all 1).

    Returns
    -------
    ndarray, shape (4, 4); all NaN with fewer than 3 markers seen.
    """
    reference = np.asarray(reference_model, dtype=np.float64) * model_scale
    rigid = umeyama(reference, points_world, with_scale=False, weights=weights)
    rigid[:3, :3] *= model_scale  # R diag(s, s, s): the model's scale on the rotation's columns
    return rigid
