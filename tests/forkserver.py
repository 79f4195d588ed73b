"""``python -m MODULE ARGS`` for the end-to-end tests without paying for torch, Lightning and MLflow's imports in
every process: a warm interpreter (one per test process, started on first use) imports those libraries once and
forks a child for each command. The child is set up as ``python -m`` sets up a fresh process (working directory,
environment, ``sys.argv``, ``sys.path[0]``, stdin from /dev/null, stdout and stderr to files), runs the module as
``__main__`` and exits as an interpreter does (threads joined, ``atexit``, exit status, traceback of an uncaught
exception) but for tearing down its modules, which takes seconds with torch loaded. Only third-party libraries are
imported ahead; ``ablate`` itself is imported by each child, as by a fresh process.

Importing those libraries takes about 4 s a process, which is most of what a smoke job costs. Tests about how a
command imports (tests/test_commands.py, tests/test_layers.py) or about signals to a command
(tests/test_preemption.py, tests/test_tracking_outage.py) start processes of their own. ``ABLATE_TESTS_FORK=0``
runs every command in a fresh interpreter instead.
"""

from __future__ import annotations

import atexit
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

#: What the warm interpreter imports: the libraries a job imports that take longest (``python -X importtime``).
PRELOAD = [
    "numpy",
    "torch",
    "lightning.pytorch",
    "torchmetrics",
    "scipy.stats",
    "scipy.signal",
    "pandas",
    "matplotlib",
    "sqlalchemy",
    "mlflow",
    "mlflow.tracking",
    "mlflow.store.tracking.sqlalchemy_store",
    "hydra",
    "omegaconf",
]

#: The warm interpreter: imports PRELOAD, then forks a child per request on the Unix socket argv[1] and tells the
#: client the child's pid, then its exit status. It ends when its stdin closes (the test process is gone).
SERVER = r"""
import importlib, json, os, selectors, socket, sys

for name in sys.argv[2].split(","):
    importlib.import_module(name)

listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
listener.bind(sys.argv[1])
listener.listen(16)
sys.stdout.write("ready\n")
sys.stdout.flush()


def serve():
    # returns in a forked child only, with its request; the parent loops until its stdin closes
    selector = selectors.DefaultSelector()
    selector.register(listener, selectors.EVENT_READ)
    selector.register(sys.stdin, selectors.EVENT_READ)
    waiting = {}
    while True:
        for key, _ in selector.select(timeout=0.05):
            if key.fileobj is sys.stdin:
                if not os.read(sys.stdin.fileno(), 1 << 16):
                    os._exit(0)
                continue
            conn, _ = listener.accept()
            request = json.loads(conn.makefile("r").readline())
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
            if pid == 0:
                selector.close()
                for other in (listener, conn, *waiting.values()):
                    other.close()
                return request
            conn.sendall(f"{pid}\n".encode())
            waiting[pid] = conn
        while waiting:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            conn = waiting.pop(pid, None)
            if conn is not None:
                try:
                    conn.sendall(f"{os.waitstatus_to_exitcode(status)}\n".encode())
                except OSError:
                    pass
                conn.close()


request = serve()
del serve
os.chdir(request["cwd"])
os.environ.clear()
os.environ.update(request["env"])
null = os.open(os.devnull, os.O_RDONLY)
os.dup2(null, 0)
os.close(null)
for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
    out = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.dup2(out, fd)
    os.close(out)
sys.path[0] = os.getcwd()  # as `python -m` puts it there
import multiprocessing.process

multiprocessing.process.ORIGINAL_DIR = os.getcwd()  # read at import; a spawned child finds its main module by it
sys.argv = [request["module"], *request["args"]]
import runpy

try:
    runpy.run_module(request["module"], run_name="__main__", alter_sys=True)
    code = 0
except SystemExit as exit:  # as the interpreter ends on it
    code = exit.code
    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
except BaseException:
    sys.excepthook(*sys.exc_info())
    code = 1
# what the interpreter does at its end up to tearing down the modules (seconds with torch loaded, and nothing a
# command's result depends on): join the threads, run the atexit functions, flush stdout and stderr
import atexit, threading

threading._shutdown()
atexit._run_exitfuncs()
for stream in (sys.stdout, sys.stderr):
    try:
        stream.flush()
    except Exception:
        pass
os._exit(code & 0xFF)
"""


class ForkServer:
    """The warm interpreter of this test process."""

    def __init__(self, env: dict[str, str]) -> None:
        self.folder = Path(tempfile.mkdtemp(prefix="ablate-fork-"))
        self.socket = str(self.folder / "s")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", SERVER, self.socket, ",".join(PRELOAD)],
            cwd=self.folder,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        ready = self.proc.stdout.readline()
        if ready != "ready\n":
            raise RuntimeError(f"the fork server did not start (exit status {self.proc.wait()})")
        self.lock = threading.Lock()
        self.count = 0

    def close(self) -> None:
        self.proc.stdin.close()  # it exits when its stdin closes
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        shutil.rmtree(self.folder, ignore_errors=True)

    def run(
        self, cwd: Path, module: str, args: list[str], env: dict[str, str], timeout: float
    ) -> subprocess.CompletedProcess:
        """``python -m module args`` in ``cwd`` with ``env``, as :func:`subprocess.run` with ``capture_output=True,
        text=True, timeout=timeout`` runs it."""
        with self.lock:
            self.count += 1
            stdout, stderr = self.folder / f"{self.count}.out", self.folder / f"{self.count}.err"
        request = {"cwd": str(cwd), "module": module, "args": list(args), "env": env}
        request |= {"stdout": str(stdout), "stderr": str(stderr)}
        cmd = [sys.executable, "-m", module, *args]
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.connect(self.socket)
            conn.sendall((json.dumps(request) + "\n").encode())
            pid = int(_line(conn))
            conn.settimeout(timeout)
            try:
                code = int(_line(conn))
            except TimeoutError:
                os.kill(pid, signal.SIGKILL)  # as subprocess.run does on a timeout
                conn.settimeout(None)
                _line(conn)
                out, err = self._read(stdout), self._read(stderr)
                raise subprocess.TimeoutExpired(cmd, timeout, out, err) from None
        return subprocess.CompletedProcess(cmd, code, self._read(stdout), self._read(stderr))

    @staticmethod
    def _read(path: Path) -> str:
        """A captured stream as ``text=True`` decodes it (the locale's encoding, universal newlines); removed."""
        try:
            return path.read_text()
        finally:
            path.unlink(missing_ok=True)


def _line(conn: socket.socket) -> str:
    """One line the server sent on ``conn`` (a pid or an exit status)."""
    data = b""
    while not data.endswith(b"\n"):
        chunk = conn.recv(1)
        if not chunk:
            raise RuntimeError("the fork server closed the connection")
        data += chunk
    return data.decode()


_server: ForkServer | None = None


def run(cwd: Path, module: str, args: list[str], env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    """``python -m module args`` in ``cwd`` with exactly the environment ``env``: forked from this test process's
    warm interpreter, or in a fresh one with ``ABLATE_TESTS_FORK=0``."""
    global _server
    if os.environ.get("ABLATE_TESTS_FORK", "1") == "0":
        return subprocess.run(
            [sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
        )
    if _server is None:
        base = {k: v for k, v in env.items() if not k.startswith(("MLFLOW_", "RAY_"))}
        _server = ForkServer(base)
        atexit.register(_server.close)
    return _server.run(cwd, module, args, env, timeout)
