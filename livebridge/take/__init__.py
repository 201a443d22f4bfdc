"""Takes: everything that reads or writes a recorded or simulated performance, one module per format.

- :mod:`~livebridge.take.npz`: the ``.npz`` take (:class:`~livebridge.take.npz.Take`): per-frame marker
  data and ground truth, for the offline tools;
- :mod:`~livebridge.take.directory`: the take directory a live run records (layout, ``take.toml``,
  :func:`~livebridge.take.directory.load_take_dir`);
- :mod:`~livebridge.take.recorder`: :class:`~livebridge.take.recorder.TakeRecorder`, which writes a take
  directory while the pipeline runs;
- :mod:`~livebridge.take.raw_frames`: raw camera frames on disk (image folders or videos and timestamp
  files) and their writer;
- :mod:`~livebridge.take.replay`: raw frames played back as camera sources (``replay://``);
- :mod:`~livebridge.take.phone`: a phone take's Live Link Face packets (``arkit.csv``), and
  :mod:`~livebridge.take.phone_replay`: a phone take played back as the phone (``[source] url = "replay://..."``);
- :mod:`~livebridge.take.trajectories`: :class:`~livebridge.take.trajectories.Trajectories` (labelled markers
  over time, any system) and ``read_trajectories`` / ``write_trajectories`` by suffix;
- :mod:`~livebridge.take.c3d`: labelled markers as C3D (``markers.c3d``, ``livebridge take export-c3d``) and
  other systems' C3D files read;
- :mod:`~livebridge.take.trc`: TRC files (OpenSim, Pose2Sim, Motive), read and written;
- :mod:`~livebridge.take.marker_csv`: marker CSV files (one column per coordinate; OpenFace), read and written;
- :mod:`~livebridge.take.text_table`: shared by the text readers (files are written with :mod:`livebridge.atomic`).
"""
