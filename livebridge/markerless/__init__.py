"""Markerless capture (CoArt): co-articulation regions of the face classified into muscle states.

One camera films the face; a head rig of four LEDs (or a fixed crop) gives the canonical pose; each
co-articulation region (CR) of the pose- and lighting-normalised image is classified into a muscle state
by its ICA signature. Modules: :mod:`normalise` (pose warp, Laplacian), :mod:`gestures` (bounded
gestures of a training take), :mod:`regions` (regions of influence, CRs), :mod:`signatures` (ICA/PCA
bases, back-substitution matrix), :mod:`train`, :mod:`model` (the trained model, .npz), :mod:`analysis`
(per-frame states and contractions), :mod:`report` (a PNG of the model), :mod:`front` (the live front).
"""
