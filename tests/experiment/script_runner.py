"""``run_script(path, *args, cwd=...)``: ``python <path> <args>`` run as a user types it, in a process forked
from a helper that has already imported torch, TorchRL, Hydra and the package (about 6 s a run on two cores).

The child does what the interpreter does for a script: ``sys.argv``, ``sys.path[0]`` and the working
directory are the script's, the script runs as ``__main__``, ``SystemExit`` gives the exit status, an
uncaught exception prints its traceback and gives 1, the ``atexit`` functions run, and its stdin is
/dev/null. Its stdout and stderr are captured as ``subprocess.run(..., capture_output=True)`` would. The
helper only imports; nothing it runs for one script is seen by the next."""

from __future__ import annotations

import atexit
import json
import subprocess
import sys
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_SERVER = r"""
import json, os, runpy, signal, sys, tempfile, time, traceback
import torch, torchrl, hydra  # noqa: F401  the slow imports every script makes
import hfrl_torch.experiment.cli, hfrl_torch.experiment.config, hfrl_torch.experiment.train  # noqa: F401
import hfrl_torch.experiment.evaluate  # noqa: F401
requests, replies = sys.stdin, os.fdopen(os.dup(1), "w")
os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
for line in requests:
    job = json.loads(line)
    out, err = tempfile.mkstemp(), tempfile.mkstemp()
    pid = os.fork()
    if pid == 0:
        code = 0
        try:
            null = os.open(os.devnull, os.O_RDONLY)
            os.dup2(null, 0)
            os.dup2(out[0], 1)
            os.dup2(err[0], 2)
            sys.stdin = open(0, closefd=False)
            os.chdir(job["cwd"])
            sys.argv = [job["script"], *job["args"]]
            sys.path[0] = os.path.dirname(job["script"])
            runpy.run_path(job["script"], run_name="__main__")
        except SystemExit as stop:
            if stop.code is None:
                code = 0
            elif isinstance(stop.code, int):
                code = stop.code
            else:
                print(stop.code, file=sys.stderr)
                code = 1
        except BaseException:
            traceback.print_exc()
            code = 1
        try:
            import atexit
            atexit._run_exitfuncs()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    deadline, timed_out = time.monotonic() + job["timeout"], False
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0:
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            done, timed_out = os.waitpid(pid, 0), True
            break
        time.sleep(0.02)
    status = os.waitstatus_to_exitcode(done[1])
    texts = []
    for fd, path in (out, err):
        os.close(fd)
        with open(path, errors="replace") as f:
            texts.append(f.read())
        os.unlink(path)
    reply = {"returncode": status, "stdout": texts[0], "stderr": texts[1], "timed_out": timed_out}
    replies.write(json.dumps(reply) + "\n")
    replies.flush()
"""

_lock = threading.Lock()
_server: subprocess.Popen | None = None


def _start() -> subprocess.Popen:
    global _server
    if _server is None or _server.poll() is not None:
        _server = subprocess.Popen(
            [sys.executable, "-c", _SERVER],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        atexit.register(_server.kill)
    return _server


def run_script(
    script: str | Path, *args: str, cwd: str | Path = ROOT, timeout: float = 300
) -> subprocess.CompletedProcess:
    """``python <script> <args>`` in ``cwd``; its exit status, stdout and stderr (``TimeoutExpired`` after
    ``timeout`` seconds, the script killed)."""
    path = str(Path(script) if Path(script).is_absolute() else ROOT / script)
    with _lock:
        server = _start()
        server.stdin.write(
            json.dumps({"script": path, "args": list(args), "cwd": str(cwd), "timeout": timeout}) + "\n"
        )
        server.stdin.flush()
        line = server.stdout.readline()
    if not line:
        raise RuntimeError("the script runner died")
    reply = json.loads(line)
    command = [sys.executable, path, *args]
    if reply.pop("timed_out"):
        raise subprocess.TimeoutExpired(command, timeout, reply["stdout"], reply["stderr"])
    return subprocess.CompletedProcess(command, **reply)
