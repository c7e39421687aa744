"""The application wing: what runs something and writes a folder (docs/architecture.md).

- :mod:`mgso.app.cli`: the ``mgso`` command line (printing, progress bars, exit codes);
- :mod:`mgso.app.stages`: the stages of ``mgso run`` (check, tracking, odometry, full), one path for every way a run
  ends;
- :mod:`mgso.app.outputs`: the outputs and evaluation of a full run;
- :mod:`mgso.app.writer`: the run writer, the one owner of an output folder;
- :mod:`mgso.app.signals`: Ctrl-C, SIGTERM and SIGHUP as one kind of interrupt, and the exit codes for them;
- :mod:`mgso.app.export`: ``mgso export`` (COLMAP and nerfstudio from a run folder);
- :mod:`mgso.app.viewer`: the live browser viewer (viser) of ``mgso run --viewer`` and ``mgso view``;
- :mod:`mgso.app.bench`, :mod:`mgso.app.bench_spec`, :mod:`mgso.app.bench_report`: ``mgso bench`` (many runs on
  Ray, the spec and its checks, the table, summary and plots).

The domain rooms below (:mod:`mgso.tracking`, :mod:`mgso.window`, :mod:`mgso.mapping`, :mod:`mgso.system`,
:mod:`mgso.io`, :mod:`mgso.eval`, ...) never import this package (tests/test_layering.py).
"""
