

SHIPPED_MARKER_SETS = ("builtin", "builtin-68", "ict-68")
"""Marker sets accepted by name wherever a marker-set file is (``--markers``, a session's ``[face] markers``):
``builtin`` (the designed layout of the built-in face), ``builtin-68`` (the 68 Multi-PIE/iBUG landmarks on the
built-in face) and ``ict-68`` (the same 68 landmarks on the ICT-FaceKit face region, as
``livebridge basis import choe-ko-ict`` builds it). Resolved by :func:`livebridge.face.shipped.load_marker_set`
(defined here so the command line names them without importing numpy)."""
