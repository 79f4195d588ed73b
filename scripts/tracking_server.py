"""A shared MLflow tracking store on this machine: PostgreSQL + ``mlflow server``, on 127.0.0.1 only.

    python scripts/tracking_server.py start DIR [--port 5000] [--pg-port 5433] [--workers 2] [--jobs]
    python scripts/tracking_server.py status DIR
    python scripts/tracking_server.py stop DIR

``start`` creates a PostgreSQL cluster in ``DIR/pgdata`` the first time (``initdb``; password authentication, the
password in ``DIR/pg.password``, readable by you alone), starts it listening on 127.0.0.1 only, then starts ``mlflow
server`` with that database as its backend store and ``DIR/artifacts`` as its artifact store, served through the
server (``--artifacts-destination``; the default ``--serve-artifacts``), and prints the ``MLFLOW_TRACKING_URI`` to
use. ``stop`` stops both (the data stays for the next ``start``). Logs: ``DIR/postgres.log``, ``DIR/mlflow.log``.
The server needs ``pip install -e .[server]`` (psycopg 3, SQLAlchemy's PostgreSQL driver). PostgreSQL refuses to
run as root: as root, its commands run as the user ``postgres`` (``runuser``), who must be able to reach ``DIR``.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

STATE = "server.json"
PG_USER, PG_DB = "ablate", "mlflow"


class ServerError(RuntimeError):
    """The store could not be started or stopped; the message says why."""


def pg_bin(name: str) -> str:
    """A PostgreSQL program: on PATH, else in the newest /usr/lib/postgresql/*/bin (Debian's layout)."""
    found = shutil.which(name) or next(iter(sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)), None)
    if not found:
        raise ServerError(f"PostgreSQL's {name} was not found: install PostgreSQL (Debian: apt-get install postgresql)"
                          " or put its bin/ folder on PATH")
    return found


def as_pg_user(cmd: list[str]) -> list[str]:
    """``cmd`` as the user ``postgres`` when we are root (PostgreSQL refuses to run as root), else as it is."""
    return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd


def run(cmd: list[str], env: dict | None = None) -> None:
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise ServerError(f"{' '.join(cmd[:6])} ... failed ({out.returncode}): {(out.stderr or out.stdout).strip()}")


def init_cluster(folder: Path, pg_port: int) -> str:
    """Create ``folder/pgdata`` and the ``mlflow`` database the first time; return the database password."""
    pgdata, pwfile = folder / "pgdata", folder / "pg.password"
    if (pgdata / "PG_VERSION").exists():
        return pwfile.read_text().strip()
    password = secrets.token_urlsafe(24)
    pgdata.mkdir(mode=0o700)
    tmp_pw = folder / "pg.initpw"  # for initdb alone, removed once it has run
    tmp_pw.write_text(password + "\n")
    tmp_pw.chmod(0o600)
    if os.geteuid() == 0:
        shutil.chown(pgdata, "postgres", "postgres")
        shutil.chown(tmp_pw, "postgres", "postgres")
    check = subprocess.run(as_pg_user(["test", "-w", str(pgdata)]))
    if check.returncode != 0:
        shutil.rmtree(pgdata)
        tmp_pw.unlink()
        raise ServerError(f"the user postgres cannot reach {pgdata}: choose a DIR whose parent folders it may enter "
                          "(not under /root, say)")
    try:
        run(as_pg_user([pg_bin("initdb"), "-D", str(pgdata), "-U", PG_USER, f"--pwfile={tmp_pw}",
                        "--auth=scram-sha-256", "--encoding=UTF8", "--no-instructions"]))
    except ServerError:
        shutil.rmtree(pgdata, ignore_errors=True)
        raise
    finally:
        tmp_pw.unlink()
    pwfile.write_text(password + "\n")
    pwfile.chmod(0o600)
    start_postgres(folder, pg_port)
    run([pg_bin("createdb"), "-h", "127.0.0.1", "-p", str(pg_port), "-U", PG_USER, PG_DB],
        env={**os.environ, "PGPASSWORD": password})
    return password


def start_postgres(folder: Path, pg_port: int) -> None:
    """Start the cluster on 127.0.0.1:``pg_port`` (no Unix socket), waiting until it accepts connections."""
    pgdata = folder / "pgdata"
    if (pgdata / "postmaster.pid").exists():
        return
    log = folder / "postgres.log"
    if not log.exists():
        log.touch()
    if os.geteuid() == 0:
        shutil.chown(log, "postgres", "postgres")
    options = f"-c listen_addresses=127.0.0.1 -p {pg_port} -c unix_socket_directories=''"
    run(as_pg_user([pg_bin("pg_ctl"), "-D", str(pgdata), "-l", str(log), "-w", "-t", "60", "-o", options, "start"]))


def wait_healthy(url: str, proc: subprocess.Popen, log: Path, timeout_s: float = 180) -> None:
    """Wait until ``url``/health answers 200, or fail with the server log's tail if it exits or times out."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise ServerError(f"mlflow server exited ({proc.returncode}); {log}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2) as answer:
                if answer.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise ServerError(f"mlflow server did not answer at {url} within {timeout_s:.0f} s; see {log}")


def start(folder: Path, port: int, pg_port: int, workers: int, jobs: bool = False) -> dict:
    """Start PostgreSQL and ``mlflow server``; return the state written to ``folder/server.json``."""
    folder = folder.resolve()
    if (folder / STATE).exists():
        state = json.loads((folder / STATE).read_text())
        if alive(state["mlflow_pid"]):
            raise ServerError(f"already running from {folder}: {state['tracking_uri']} (stop it first)")
    folder.mkdir(parents=True, exist_ok=True)
    password = init_cluster(folder, pg_port)
    start_postgres(folder, pg_port)
    log = folder / "mlflow.log"
    url = f"http://127.0.0.1:{port}"
    mlflow = Path(sys.executable).with_name("mlflow")
    cmd = [str(mlflow) if mlflow.exists() else "mlflow", "server",
           "--backend-store-uri", f"postgresql+psycopg://{PG_USER}@127.0.0.1:{pg_port}/{PG_DB}",
           "--artifacts-destination", str(folder / "artifacts"),
           "--host", "127.0.0.1", "--port", str(port), "--workers", str(workers)]
    # The password reaches psycopg through libpq's PGPASSWORD, not the command line. MLflow's server-side job runner
    # (huey consumers for its GenAI features; MLFLOW_SERVER_ENABLE_JOB_EXECUTION, on by default) is off unless asked
    # for: tracking never uses it, and it adds seven processes.
    env = {**os.environ, "PGPASSWORD": password, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "true" if jobs else "false"}
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, env=env)
    state = {"tracking_uri": url, "mlflow_pid": proc.pid, "port": port, "pg_port": pg_port,
             "pgdata": str(folder / "pgdata"), "artifacts": str(folder / "artifacts")}
    (folder / STATE).write_text(json.dumps(state, indent=1))
    try:
        wait_healthy(url, proc, log)
    except ServerError:
        stop(folder)
        raise
    return state


def alive(pid: int) -> bool:
    """Whether ``pid`` is a running ``mlflow server`` (not a reused pid)."""
    try:
        return b"mlflow" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def stop(folder: Path) -> bool:
    """Stop the ``mlflow server`` and the PostgreSQL cluster started from ``folder``; False if none was running."""
    folder = folder.resolve()
    path = folder / STATE
    if not path.exists():
        return False
    state = json.loads(path.read_text())
    pid = int(state["mlflow_pid"])
    if alive(pid):
        os.killpg(pid, signal.SIGTERM)  # the server and its workers: a session of their own, started above
        deadline = time.monotonic() + 30
        while alive(pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        if alive(pid):
            os.killpg(pid, signal.SIGKILL)
    pgdata = Path(state["pgdata"])
    if (pgdata / "postmaster.pid").exists():
        run(as_pg_user([pg_bin("pg_ctl"), "-D", str(pgdata), "-m", "fast", "-w", "stop"]))
    path.unlink()
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=["start", "stop", "status"])
    parser.add_argument("dir", type=Path, help="folder of the database, the artifacts, the logs and the state")
    parser.add_argument("--port", type=int, default=5000, help="mlflow server's port on 127.0.0.1")
    parser.add_argument("--pg-port", type=int, default=5433, help="PostgreSQL's port on 127.0.0.1")
    parser.add_argument("--workers", type=int, default=2, help="mlflow server's worker processes")
    parser.add_argument("--jobs", action="store_true", help="start MLflow's server-side job runner too")
    args = parser.parse_args(argv)
    try:
        if args.action == "start":
            state = start(args.dir, args.port, args.pg_port, args.workers, args.jobs)
            print(f"export MLFLOW_TRACKING_URI={state['tracking_uri']}")
        elif args.action == "stop":
            print("stopped" if stop(args.dir) else f"nothing running from {args.dir}")
        else:
            path = args.dir / STATE
            state = json.loads(path.read_text()) if path.exists() else None
            running = state is not None and alive(state["mlflow_pid"])
            print(f"running: {state['tracking_uri']}" if running else "not running")
            return 0 if running else 3
    except ServerError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
