"""``python -m MODULE ARGS`` for the end-to-end tests without paying for torch, Lightning and MLflow's imports in
every process: a warm interpreter (one per test process, started on first use) imports those libraries once and
forks a child for each command. The child is set up as ``python -m`` sets up a fresh process (working directory,
environment, ``sys.argv``, ``sys.path[0]``, stdin from /dev/null, stdout and stderr to files), runs the module as
``__main__`` and exits as an interpreter does (threads joined, ``atexit``, exit status, traceback of an uncaught
exception) but for tearing down its modules, which takes seconds with torch loaded. Only third-party libraries are
imported ahead; ``ablate`` itself is imported by each child, as by a fresh process. The warm interpreter also runs
a job's kinds of MLflow queries once on a throwaway store, so that SQLAlchemy's per-class compilers are built
before the forks (a forked job then takes 2.2 s instead of 2.5 s on a 2-core AMD EPYC family 25 model 17).

Importing those libraries takes about 4 s a process, which is most of what a smoke job costs. Tests about how a
command imports (tests/test_commands.py, tests/test_layers.py) or about signals to a command
(tests/test_preemption.py, tests/test_tracking_outage.py) start processes of their own. ``ABLATE_TESTS_FORK=0``
runs every command in a fresh interpreter instead.
"""

from __future__ import annotations

import atexit
import functools
import itertools
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
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


def warm_the_store():
    # the first queries of a process against any MLflow store build SQLAlchemy's per-class compilers and cache-key
    # functions (0.6 s, then 0.05 s a store): done here once, on a throwaway store, for every forked command; its
    # engine is closed before the first fork (a child opens its own store, as a fresh process does)
    from mlflow.entities import Metric, Param, RunTag
    from mlflow.tracking import MlflowClient

    client = MlflowClient("sqlite:///" + os.path.join(os.getcwd(), "warm.db"))
    experiment = client.create_experiment("warm")
    client.get_experiment_by_name("warm")
    run = client.create_run(experiment, tags={"kind": "job", "row": "a"}).info.run_id
    client.log_batch(run, metrics=[Metric("m", 1.0, 0, 0)], params=[Param("p", "1")], tags=[RunTag("t", "1")])
    client.search_runs([experiment], "tags.kind = 'job' and params.p = '1' and attributes.status = 'RUNNING'",
                       order_by=["attributes.start_time DESC"])
    client.get_metric_history(run, "m")
    client.set_terminated(run)
    client.get_run(run)
    client.search_experiments()
    client._tracking_client.store.engine.dispose()
    os.remove("warm.db")


warm_the_store()
del warm_the_store

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
script = request["module"].endswith(".py")
# where `python -m` puts the working directory, `python SCRIPT` the script's folder
sys.path[0] = os.path.dirname(os.path.abspath(request["module"])) if script else os.getcwd()
import multiprocessing.process

multiprocessing.process.ORIGINAL_DIR = os.getcwd()  # read at import; a spawned child finds its main module by it
sys.argv = [request["module"], *request["args"]]
import runpy

try:
    if script:
        runpy.run_path(request["module"], run_name="__main__")
    else:
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
        self.count = itertools.count()

    def close(self) -> None:
        self.proc.stdin.close()  # it exits when its stdin closes
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        shutil.rmtree(self.folder, ignore_errors=True)


class Command:
    """A command started by :func:`start`, used as a :class:`subprocess.Popen` (``pid``, ``args``, ``returncode``,
    ``poll``, ``wait``, ``send_signal``, ``terminate``, ``kill``, ``communicate``). Its stdout and stderr go to
    files; :meth:`communicate` returns their text (and removes them) where :func:`start` chose them."""

    def __init__(
        self, cwd: Path, module: str, args: list[str], env: dict[str, str], stdout: Path | None, stderr: Path | None
    ) -> None:
        self.args = [sys.executable, *([] if module.endswith(".py") else ["-m"]), module, *args]
        self.returncode: int | None = None
        server = _server_for(env)
        n = next(server.count) if server else 0
        folder = server.folder if server else _scratch()
        self.captured = stdout is None
        self.stdout, self.stderr = stdout or folder / f"{n}.out", stderr or folder / f"{n}.err"
        if server is None:
            with open(self.stdout, "w") as out, open(self.stderr, "w") as err:
                self._popen: subprocess.Popen | None = subprocess.Popen(
                    self.args, cwd=cwd, env=env, stdout=out, stderr=err
                )
            self.pid = self._popen.pid
            return
        self._popen = None
        request = {"cwd": str(cwd), "module": module, "args": list(args), "env": env}
        request |= {"stdout": str(self.stdout), "stderr": str(self.stderr)}
        self._conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._conn.connect(server.socket)
        self._conn.sendall((json.dumps(request) + "\n").encode())
        self._answer = b""
        self.pid = int(self._line(None))

    def _line(self, timeout: float | None) -> str:
        """The next line the server sends (a pid, then an exit status), waiting up to ``timeout`` seconds."""
        self._conn.settimeout(timeout)
        try:
            while b"\n" not in self._answer:
                chunk = self._conn.recv(64)
                if not chunk:
                    raise RuntimeError("the fork server closed the connection")
                self._answer += chunk
        finally:
            self._conn.settimeout(None)
        line, self._answer = self._answer.split(b"\n", 1)
        return line.decode()

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                self.wait(timeout=0)
            except subprocess.TimeoutExpired:
                pass
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is not None:
            return self.returncode
        if self._popen is not None:
            self.returncode = self._popen.wait(timeout)
            return self.returncode
        try:
            self.returncode = int(self._line(timeout))
        except (TimeoutError, BlockingIOError):
            raise subprocess.TimeoutExpired(self.args, timeout) from None
        self._conn.close()
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def communicate(self, timeout: float | None = None) -> tuple[str | None, str | None]:
        """Wait for the command: its stdout and stderr as ``text=True`` decodes them (the locale's encoding,
        universal newlines) where :func:`start` captured them, else ``(None, None)``."""
        self.wait(timeout)
        if not self.captured:
            return None, None
        out, err = self.stdout.read_text(), self.stderr.read_text()
        self.stdout.unlink(missing_ok=True)
        self.stderr.unlink(missing_ok=True)
        return out, err


_server: ForkServer | None = None


@functools.cache
def _scratch() -> Path:
    """Where a fresh process's captured output waits to be read (``ABLATE_TESTS_FORK=0``)."""
    folder = Path(tempfile.mkdtemp(prefix="ablate-cmd-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    return folder


def _server_for(env: dict[str, str]) -> ForkServer | None:
    """This test process's warm interpreter (started on first use), or None with ``ABLATE_TESTS_FORK=0``."""
    global _server
    if os.environ.get("ABLATE_TESTS_FORK", "1") == "0":
        return None
    if _server is None:
        _server = ForkServer({k: v for k, v in env.items() if not k.startswith(("MLFLOW_", "RAY_"))})
        atexit.register(_server.close)
    return _server


def start(
    cwd: Path,
    module: str,
    args: list[str],
    env: dict[str, str],
    stdout: Path | None = None,
    stderr: Path | None = None,
) -> Command:
    """``python -m module args`` (``python module args`` where ``module`` is a ``.py`` file) in ``cwd`` with exactly
    the environment ``env``, in the background, as :class:`subprocess.Popen` starts it: forked from this test process's warm interpreter, or a fresh one with
    ``ABLATE_TESTS_FORK=0``. Its stdout and stderr go to the files ``stdout`` and ``stderr``, or are captured for
    :meth:`Command.communicate`."""
    return Command(Path(cwd), module, list(args), env, stdout, stderr)


def run(cwd: Path, module: str, args: list[str], env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    """``python -m module args`` in ``cwd`` with exactly the environment ``env``, as :func:`subprocess.run` with
    ``capture_output=True, text=True, timeout=timeout`` runs it (see :func:`start`)."""
    command = start(cwd, module, args, env)
    try:
        out, err = command.communicate(timeout)
    except subprocess.TimeoutExpired:
        command.kill()  # as subprocess.run does on a timeout
        out, err = command.communicate()
        raise subprocess.TimeoutExpired(command.args, timeout, out, err) from None
    return subprocess.CompletedProcess(command.args, command.returncode, out, err)
