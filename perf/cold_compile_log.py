"""``perf/cold_progress_gaps.py`` with every Warp module's compile and load timed (which thread, how long, whether
it built): where a first run's time goes.  ``GPPS_CACHE_DIR=$(mktemp -d) python perf/cold_compile_log.py FOLDER
[--device cuda:0] > out.json``; the compile log goes to stderr as JSON lines."""
import json
import runpy
import sys
import threading
import time

import warp as wp

Module = type(wp.get_module(__name__))
T0 = time.perf_counter()
_LOCK = threading.Lock()  # (one line at a time: the helpers compile on threads of their own)


def _timed(name, fn):
    def run(self, *a, **k):
        t = time.perf_counter()
        r = fn(self, *a, **k)
        dt = time.perf_counter() - t
        if name == "load" and dt < 0.05:
            return r
        line = json.dumps({"what": name, "module": self.name, "start_s": round(t - T0, 3), "seconds": round(dt, 3),
                           "thread": threading.current_thread().name,
                           **({"built": bool(r)} if name == "compile" else {})})
        with _LOCK:
            print(line, file=sys.stderr, flush=True)
        return r
    return run


Module._compile = _timed("compile", Module._compile)
Module.load = _timed("load", Module.load)
sys.argv = ["perf/cold_progress_gaps.py"] + sys.argv[1:]
runpy.run_path("perf/cold_progress_gaps.py", run_name="__main__")
