"""Where a script's CPU time goes, kernel by kernel: runs a Python script with every Warp launch's thread CPU time
summed per kernel; prints one JSON line when the script ends (after whatever the script prints).

    python profiles/kernel_cpu.py SCRIPT [ARGS ...]
    MGSO_DATA=../shared/data python profiles/kernel_cpu.py profiles/mapping.py --one \\
        ../shared/data/7scenes_redkitchen_0-499 --source dso        # one deterministic replay of the mapper

Each launch (``wp.launch``, and the recorded launches of :func:`mgso_kernels.runtime.launch_split`'s chunks, which
run on the caller's thread and on its workers) is charged the CPU time of the thread that ran it
(``time.thread_time``), so a split launch's chunks add up over the cores. ``process_cpu_s`` is the process's CPU over
the script (kernels, Python, NumPy, OpenCV); ``kernel_cpu_s`` the launches' sum; ``kernels`` lists
``[name, calls, cpu_s]``, largest first. Launches that only record a command cost nothing here and are not counted.
Run the script's own work in this process: ``profiles/mapping.py`` needs ``--one`` (without it each variant runs in a
subprocess this wrapper does not see).
"""

from __future__ import annotations

import atexit
import collections
import json
import runpy
import sys
import threading
import time


def main() -> int:
    if len(sys.argv) < 2:
        raise SystemExit(__doc__.split("\n\n")[1])
    import warp as wp
    from warp._src import context

    acc: dict = collections.defaultdict(lambda: [0, 0.0])
    lock = threading.Lock()

    def charge(kernel, seconds: float) -> None:
        name = getattr(kernel, "key", None) or getattr(kernel, "__name__", None) or str(kernel)
        with lock:
            entry = acc[name]
            entry[0] += 1
            entry[1] += seconds

    plain = wp.launch

    def launch(kernel, *args, **kwargs):
        if kwargs.get("record_cmd"):
            return plain(kernel, *args, **kwargs)
        t = time.thread_time()
        try:
            return plain(kernel, *args, **kwargs)
        finally:
            charge(kernel, time.thread_time() - t)

    recorded = context.Launch.launch

    def launch_recorded(self, *args, **kwargs):
        t = time.thread_time()
        try:
            return recorded(self, *args, **kwargs)
        finally:
            charge(self.kernel, time.thread_time() - t)

    wp.launch = launch
    context.Launch.launch = launch_recorded
    cpu0, wall0 = time.process_time(), time.perf_counter()

    def report() -> None:
        rows = sorted(acc.items(), key=lambda kv: -kv[1][1])
        print(json.dumps({"profile": "kernel_cpu", "script": sys.argv[0], "args": sys.argv[1:],
                          "wall_s": round(time.perf_counter() - wall0, 2),
                          "process_cpu_s": round(time.process_time() - cpu0, 2),
                          "kernel_cpu_s": round(sum(s for _, s in acc.values()), 2),
                          "kernels": [[name, n, round(s, 3)] for name, (n, s) in rows]}), flush=True)

    atexit.register(report)
    sys.argv = sys.argv[1:]
    runpy.run_path(sys.argv[0], run_name="__main__")
    return 0


if __name__ == "__main__":
    sys.exit(main())
