"""Development tools: ``trifuse bench`` and the console subprocess it drives.

- ``bench.py``: the registry of benchmarks (``benchmark.py``: what one is, how it runs);
  ``bench_*.py``: the benchmarks by subject; ``bench_soak.py`` with ``soak_report.py``: the
  stream soak (``trifuse bench --soak``).
- ``console_process.py``: ``trifuse serve`` in a subprocess (started, awaited, stopped) for
  the benchmarks, the soak and the tests; ``browser_console.py``: its viewer page in
  headless Chromium; ``stream_clients.py``: clients of its stream; what ``/proc`` says
  about it is :mod:`app.procfs` (the console reads its own threads with it too).
"""
