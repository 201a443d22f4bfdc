"""2D characters driven by the face (CoArt synthesis, §6 of the paper).

A character is a neutral image and, per co-articulation region (CR) and per state of each of its muscles,
an appearance sample placed on the canvas; each frame is composited from the samples the performer's
current CR states select. Modules: :mod:`~livebridge.character.definition` (the character folder),
:mod:`~livebridge.character.alpha` (feathered alpha masks), :mod:`~livebridge.character.states` (CR states from
a frame), :mod:`~livebridge.character.composite` (the per-frame compositor),
:mod:`~livebridge.character.builtin` (a procedural cartoon face), :mod:`~livebridge.character.rewrite` (video
rewrite: a character filled from a markerless model's training frames), :mod:`~livebridge.character.template`
(guide sheets for artists), :mod:`~livebridge.character.render` (offline video),
:mod:`~livebridge.character.live` (the live output to the render client's 2D view).
"""
