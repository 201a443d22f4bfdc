"""Takes: everything that reads or writes a recorded or simulated performance.

One module per format or concept:

- :mod:`~livebridge.take.npz`: the ``.npz`` take (:class:`~livebridge.take.npz.Take`), per-frame marker
  data and ground truth, for offline tools;
- :mod:`~livebridge.take.recorder`: :class:`~livebridge.take.recorder.TakeRecorder`, which writes a take
  directory while the pipeline runs;
- :mod:`~livebridge.take.replay`: raw camera frames played back as camera sources (``replay://``).
"""
