"""ARKit weights -> muscle contractions, by solving: the weights make a face, the muscles explain it.

Per frame the 52 weights synthesise the marker displacements of an ARKit-named face on the basis's mesh
(``d_j = sum_k w_k s_kj``, :mod:`livebridge.arkit.shapes`), and the streaming contraction solver
(:class:`~livebridge.solve.solver.ContractionSolver`) finds the contractions that explain them, as it does
for markers a camera rig saw. So any basis and any marker set serve, the bounds and region modes are the
solver's, and an ARKit shape no muscle can make simply leaves a residual instead of being forced onto one.
The weights-to-displacement map is one ``(3 n_markers, 52)`` matrix, made once.
"""

from __future__ import annotations

import numpy as np

from livebridge.arkit.names import N_BLENDSHAPES
from livebridge.arkit.shapes import ArkitShapes
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.solve.solver import ContractionSolver, SolverConfig, SolveResult, SolverState


class ArkitSolver:
    """Contractions from ARKit weights for one basis, marker set and ARKit shape set.

    Parameters
    ----------
    basis : Basis
    markers : MarkerSet
        Where the synthesised face is sampled (face markers; head markers are ignored).
    shapes : ArkitShapes
        On the basis's mesh (same vertices).
    config : SolverConfig, optional
    """

    def __init__(self, basis: Basis, markers: MarkerSet, shapes: ArkitShapes, config: SolverConfig | None = None):
        if shapes.n_vertices != basis.n_vertices:
            raise InputError(f"the ARKit shapes ({shapes.source}) have {shapes.n_vertices} vertices, the basis "
                             f"{basis.n_vertices}: they must be made on the basis's mesh", field="arkit_shapes")
        self.solver = ContractionSolver(basis, markers, config)
        per_shape = markers.positions(shapes.deltas, basis.triangles)  # (52, n_markers, 3)
        per_shape[:, markers.head_mask] = 0.0
        self._shape = per_shape.shape[1:]
        self.weights_to_displacement = np.ascontiguousarray(per_shape.reshape(N_BLENDSHAPES, -1).T)

    def initial_state(self) -> SolverState:
        return self.solver.initial_state()

    def displacements(self, weights: np.ndarray) -> np.ndarray:
        """Marker displacements, shape (n_markers, 3), of the face the weights (52,) make."""
        return (self.weights_to_displacement @ np.asarray(weights, dtype=np.float64)).reshape(self._shape)

    def step(self, state: SolverState, weights: np.ndarray) -> tuple[SolverState, SolveResult]:
        """Solve one frame from its 52 ARKit weights (finite, in [0, 1])."""
        return self.solver.step(state, self.displacements(weights))
