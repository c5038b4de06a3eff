"""The study's workers: one ``train.py`` subprocess per participant in the teaching step.

A worker is launched by command line (never imported), on a free loopback port with its own token, its
run directory under the participant's, stdout and stderr to ``worker.log`` and its pid in ``worker.pid``.
It dies with the study server (Linux ``PR_SET_PDEATHSIG`` = SIGTERM, set in the child before it runs:
the signal comes when the THREAD that started it ends, so the study starts every worker from one thread
that lives as long as the study); train.py saves and stops on SIGTERM. Nothing here blocks for long:
:meth:`Worker.terminate` sends SIGTERM and :meth:`Worker.check` escalates to SIGKILL after the timeout.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hfrl_torch.study import layout

PR_SET_PDEATHSIG = 1
STOP_TIMEOUT_S = 30.0  # SIGTERM, then SIGKILL: train.py ends its chunk and saves (Tetris CE: a few seconds)
PROBE_TIMEOUT_S = 0.05
REPO = Path(__file__).resolve().parent.parent.parent
TRAIN_SCRIPT = REPO / "train.py"

try:
    _LIBC: ctypes.CDLL | None = ctypes.CDLL("libc.so.6", use_errno=True)
except OSError:  # not glibc Linux: workers then outlive a killed server (close() still stops them)
    _LIBC = None


def _die_with_parent(parent: int) -> None:
    """In the child before exec: SIGTERM when the parent goes; if it already went, now."""
    if _LIBC is not None:
        _LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)


def free_port(host: str = "127.0.0.1", avoid: set[int] | frozenset[int] = frozenset()) -> int:
    """A port nothing listens on now (the kernel's choice), not in ``avoid`` (ports handed to workers
    that may not have bound them yet)."""
    for _ in range(100):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
        if port not in avoid:
            return port
    raise OSError("no free port found in 100 tries")


def accepts(port: int, host: str = "127.0.0.1", timeout: float = PROBE_TIMEOUT_S) -> bool:
    """Whether something accepts a TCP connection on ``host:port`` (a refused one answers at once)."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def has_checkpoint(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a run train.py can resume (its last checkpoint)."""
    return (run_dir / layout.CHECKPOINT).is_file()


def holds_run(run_dir: Path) -> bool:
    """Whether train.py would refuse to start a new run in ``run_dir`` (it holds one)."""
    return (run_dir / layout.RUN_CONFIG).exists()


def alive(pid: int, script: str = "train.py") -> bool:
    """Whether process ``pid`` is running and is a ``script`` (not a later process given the same pid)."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    state = stat.rsplit(")", 1)[-1].split()[0]
    return state not in ("Z", "X") and script.encode() in cmdline


def previous_pid(pid_path: Path) -> int | None:
    """The pid a ``worker.pid`` names, when that process is still a running train.py."""
    try:
        pid = int(pid_path.read_text().strip())
    except (OSError, ValueError):
        return None
    return pid if alive(pid) else None


def wait_gone(pid_path: Path, timeout: float) -> bool:
    """Wait up to ``timeout`` s for the worker ``pid_path`` names to be gone; whether it is."""
    deadline = time.monotonic() + timeout
    while previous_pid(pid_path) is not None:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)
    return True


def _quoted(value: str) -> str:
    """A path as a Hydra override value (quoted when it holds characters Hydra's grammar reads)."""
    if all(c.isalnum() or c in "/._-" for c in value):
        return value
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def fresh_command(
    python: str,
    train_script: Path,
    overrides: Sequence[str],
    run_dir: Path,
    port: int,
    token: str,
    seed: int,
) -> list[str]:
    """The command line of a new run teaching one participant (``overrides``: the condition's, the study's
    common ones and the calibration's); ``trainer.blind``: no message of the run names its condition."""
    return [
        python,
        str(train_script),
        *overrides,
        "trainer=interactive",
        "trainer.host=127.0.0.1",
        f"trainer.port={port}",
        f"trainer.token={token}",
        "trainer.blind=true",
        f"seed={seed}",
        f"hydra.run.dir={_quoted(str(run_dir))}",
    ]


def resume_command(python: str, train_script: Path, run_dir: Path, port: int, token: str) -> list[str]:
    """The command line that continues the run in ``run_dir`` (its saved config; a new port and token, and
    ``trainer.blind`` again, for a run saved before the setting existed). ``trainer=interactive`` lets the
    command line compose (it names the saved trainer, so it changes nothing)."""
    return [
        python,
        str(train_script),
        f"resume={_quoted(str(run_dir))}",
        "trainer=interactive",
        f"trainer.port={port}",
        f"trainer.token={token}",
        "trainer.blind=true",
    ]


class Worker:
    """One train.py subprocess: started, probed for readiness, stopped (SIGTERM, then SIGKILL)."""

    def __init__(self, command: list[str], port: int, token: str, log_path: Path, pid_path: Path) -> None:
        self.command = command
        self.port = port
        self.token = token
        self.log_path = log_path
        self.pid_path = pid_path
        self.process: subprocess.Popen[bytes] | None = None
        self.ready = False
        self.stopping = False
        self.kill_at = 0.0
        self.started_at = 0.0
        self.returncode: int | None = None

    @property
    def pid(self) -> int | None:
        """The process id (None before start)."""
        return None if self.process is None else self.process.pid

    def start(self) -> None:
        """Launch the process (stdout and stderr appended to the log) and write its pid file."""
        env = dict(os.environ)
        env["PYTHONUNBUFFERED"] = "1"
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
        parent = os.getpid()
        with open(self.log_path, "ab") as log:
            log.write(f"\n# {time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(self.command)}\n".encode())
            log.flush()
            self.process = subprocess.Popen(
                self.command,
                cwd=REPO,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # the terminal's Ctrl-C reaches the study, which stops its workers
                preexec_fn=lambda: _die_with_parent(parent),
            )
        self.started_at = time.monotonic()
        layout.write_atomic(self.pid_path, f"{self.process.pid}\n")

    def check(self) -> int | None:
        """The exit status once the process has ended (None while it runs); probes readiness while it
        starts, and sends SIGKILL to a worker that outlived its stop timeout."""
        if self.process is None:
            return None
        if self.returncode is None:
            self.returncode = self.process.poll()
        if self.returncode is not None:
            return self.returncode
        if self.stopping and time.monotonic() >= self.kill_at:
            with contextlib.suppress(ProcessLookupError):
                self.process.kill()
        elif not self.ready and not self.stopping:
            self.ready = accepts(self.port)
        return None

    def terminate(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Ask the run to stop (SIGTERM: it saves); :meth:`check` kills it after ``timeout`` s."""
        if self.process is None or self.returncode is not None or self.stopping:
            return
        self.stopping = True
        self.ready = False
        self.kill_at = time.monotonic() + timeout
        with contextlib.suppress(ProcessLookupError):
            self.process.send_signal(signal.SIGTERM)

    def wait(self, timeout: float = STOP_TIMEOUT_S) -> int:
        """Stop and wait for the process: SIGTERM, SIGKILL after ``timeout`` s; its exit status."""
        assert self.process is not None
        self.terminate(timeout)
        try:
            self.returncode = self.process.wait(max(self.kill_at - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.returncode = self.process.wait()
        return self.returncode

    @property
    def state(self) -> str:
        """``starting``, ``ready``, ``stopping`` or ``exited`` (for the researcher's page)."""
        if self.returncode is not None:
            return "exited"
        if self.stopping:
            return "stopping"
        return "ready" if self.ready else "starting"


def python_default() -> str:
    """The interpreter workers run with: this one."""
    return sys.executable
