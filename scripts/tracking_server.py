"""A shared MLflow tracking store: PostgreSQL + ``mlflow server``, on 127.0.0.1 unless told otherwise.

    python scripts/tracking_server.py start DIR [--port 5000] [--pg-port 5433] [--workers 2] [--jobs]
                                                [--host ADDR --auth] [--allowed-hosts LIST]
    python scripts/tracking_server.py status DIR
    python scripts/tracking_server.py stop DIR

``start`` creates a PostgreSQL cluster in ``DIR/pgdata`` the first time (``initdb``; password authentication, the
password in ``DIR/pg.password``, readable by you alone), starts it listening on 127.0.0.1 only, then starts ``mlflow
server`` with that database as its backend store and ``DIR/artifacts`` as its artifact store, served through the
server (``--artifacts-destination``; the default ``--serve-artifacts``), and prints the ``MLFLOW_TRACKING_URI`` to
use. ``stop`` stops both (the data stays for the next ``start``). Logs: ``DIR/postgres.log``, ``DIR/mlflow.log``.
The server needs ``pip install -e .[server]`` (psycopg 3, SQLAlchemy's PostgreSQL driver; ``--auth`` also
needs ``mlflow[auth]``, for Flask-WTF). PostgreSQL refuses to
run as root: as root, its commands run as the user ``postgres`` (``runuser``), who must be able to reach ``DIR``.

Other machines, authentication. ``--host ADDR`` serves on another address than 127.0.0.1 (``0.0.0.0``: every
interface), and is refused unless ``--auth`` is given too: without it anyone who can reach the port could read,
change or delete every run. ``--auth`` serves MLflow's own basic-auth app (``mlflow server --app-name basic-auth``):

- the first ``start --auth`` generates the admin password (``secrets.token_urlsafe``) into ``DIR/auth.password`` and
  the app's session key into ``DIR/auth.secret``, both mode 0600, kept for every later start (the admin account is
  created once, with that password); the app's settings are ``DIR/basic_auth.ini`` (``MLFLOW_AUTH_CONFIG_PATH``:
  ``admin_username = admin``, ``default_permission = READ``), its users and permissions a database
  ``mlflow_auth`` in the same PostgreSQL cluster (``database_uri``);
- ``start`` prints the lines to give jobs, naming the password file, never the password::

      export MLFLOW_TRACKING_URI=http://HOST:5000
      export MLFLOW_TRACKING_USERNAME=admin
      export MLFLOW_TRACKING_PASSWORD="$(cat DIR/auth.password)"

  MLflow's client reads the last two itself, for every request a job makes, its artifacts included. On another
  machine, copy the file there (``scp``, then ``chmod 600``), or give each user an account of their own::

      from mlflow.server import get_app_client
      get_app_client("basic-auth", tracking_uri=URI).create_user("alice", "<a password>")  # as admin

  A user reads every experiment (``default_permission = READ``) and manages the ones they create; to let a user log
  to a table another user created, grant it (``update_experiment_permission``, or ``create_experiment_permission``
  with ``EDIT``), or run every job as one account. A client without credentials gets HTTP 401.
- MLflow answers only requests whose Host header it expects (DNS-rebinding protection): localhost and private
  addresses (10.*, 172.16-31.*, 192.168.*) by default, plus, here, the name ``start`` prints (with ``--host 0.0.0.0``,
  the machine's host name, and its addresses). Clients that reach the server by another name need it in
  ``--allowed-hosts`` (``name,name:*``, replacing the list); a refused Host header is HTTP 403.

TLS. Basic auth sends the password with every request, readable on the network unless it is encrypted: outside a
trusted network put a TLS reverse proxy in front and leave ``mlflow server`` on 127.0.0.1 (still with ``--auth``: the
proxy makes it reachable). Caddy, which fetches and renews the certificate itself (``/etc/caddy/Caddyfile``)::

    mlflow.example.org {
        reverse_proxy 127.0.0.1:5000 {
            header_up Host {upstream_hostport}
        }
    }

or nginx (its default Host header to the upstream is ``127.0.0.1:5000``, which MLflow accepts)::

    server {
        listen 443 ssl;
        server_name mlflow.example.org;
        ssl_certificate     /etc/ssl/mlflow.example.org.crt;
        ssl_certificate_key /etc/ssl/mlflow.example.org.key;
        client_max_body_size 0;           # checkpoints and other artifacts go through the server
        location / {
            proxy_pass http://127.0.0.1:5000;
            proxy_read_timeout 600s;
        }
    }

and jobs use ``MLFLOW_TRACKING_URI=https://mlflow.example.org`` with the same two credential variables (for a
certificate of your own CA, ``MLFLOW_TRACKING_SERVER_CERT_PATH`` names the CA's file).
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import ipaddress
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

STATE = "server.json"
PG_USER, PG_DB, AUTH_DB = "ablate", "mlflow", "mlflow_auth"
AUTH_USER, AUTH_PASSWORD, AUTH_SECRET, AUTH_INI = "admin", "auth.password", "auth.secret", "basic_auth.ini"


class ServerError(RuntimeError):
    """The store could not be started or stopped; the message says why."""


def pg_bin(name: str) -> str:
    """A PostgreSQL program: on PATH, else in the newest /usr/lib/postgresql/*/bin (Debian's layout)."""
    found = shutil.which(name) or next(iter(sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)), None)
    if not found:
        raise ServerError(
            f"PostgreSQL's {name} was not found: install PostgreSQL (Debian: apt-get install postgresql)"
            " or put its bin/ folder on PATH"
        )
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
        raise ServerError(
            f"the user postgres cannot reach {pgdata}: choose a DIR whose parent folders it may enter "
            "(not under /root, say)"
        )
    try:
        run(
            as_pg_user(
                [
                    pg_bin("initdb"),
                    "-D",
                    str(pgdata),
                    "-U",
                    PG_USER,
                    f"--pwfile={tmp_pw}",
                    "--auth=scram-sha-256",
                    "--encoding=UTF8",
                    "--no-instructions",
                ]
            )
        )
    except ServerError:
        shutil.rmtree(pgdata, ignore_errors=True)
        raise
    finally:
        tmp_pw.unlink()
    pwfile.write_text(password + "\n")
    pwfile.chmod(0o600)
    start_postgres(folder, pg_port)
    run(
        [pg_bin("createdb"), "-h", "127.0.0.1", "-p", str(pg_port), "-U", PG_USER, PG_DB],
        env={**os.environ, "PGPASSWORD": password},
    )
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


def is_loopback(host: str) -> bool:
    """Whether every address ``host`` names is a loopback one (127.0.0.0/8, ::1); ``0.0.0.0`` and ``::`` are not."""
    try:
        infos = socket.getaddrinfo(host, None)
    except socket.gaierror as err:
        raise ServerError(f"--host {host}: not an address of this machine ({err.strerror})") from None
    return all(ipaddress.ip_address(info[4][0].split("%")[0]).is_loopback for info in infos)


def is_wildcard(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return False


def private_file(path: Path, make) -> str:
    """The stripped text of ``path``, written first as ``make()`` if it does not exist; mode 0600 either way (created
    so, never readable by others for a moment)."""
    if not path.exists():
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(make() + "\n")
    path.chmod(0o600)
    return path.read_text().strip()


def ensure_database(pg_port: int, password: str, name: str) -> None:
    """Create the database ``name`` in the cluster unless it exists."""
    out = subprocess.run(
        [pg_bin("createdb"), "-h", "127.0.0.1", "-p", str(pg_port), "-U", PG_USER, name],
        capture_output=True,
        text=True,
        env={**os.environ, "PGPASSWORD": password},
    )
    if out.returncode != 0 and "already exists" not in out.stderr:
        raise ServerError(f"createdb {name} failed ({out.returncode}): {out.stderr.strip()}")


def auth_setup(folder: Path, pg_port: int, password: str) -> dict[str, str]:
    """The environment of MLflow's basic-auth app: its settings file, its database in the cluster, the admin password
    and the session key (generated the first time into files readable by the user alone)."""
    ensure_database(pg_port, password, AUTH_DB)
    admin = private_file(folder / AUTH_PASSWORD, lambda: secrets.token_urlsafe(24))
    secret = private_file(folder / AUTH_SECRET, lambda: secrets.token_urlsafe(32))
    ini = folder / AUTH_INI
    ini.write_text(
        "[mlflow]\n"
        "default_permission = READ\n"
        f"database_uri = postgresql+psycopg://{PG_USER}@127.0.0.1:{pg_port}/{AUTH_DB}\n"
        f"admin_username = {AUTH_USER}\n"
        "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n"
    )
    ini.chmod(0o600)
    return {
        "MLFLOW_AUTH_CONFIG_PATH": str(ini),
        "MLFLOW_AUTH_ADMIN_PASSWORD": admin,
        "MLFLOW_FLASK_SERVER_SECRET_KEY": secret,
    }


def allowed_hosts(host: str, name: str) -> str:
    """``--allowed-hosts``: MLflow's default Host headers (localhost, private addresses), ``name`` and, serving on
    every interface, this machine's addresses; each alone and with a port (fnmatch patterns)."""
    from mlflow.server.security_utils import get_default_allowed_hosts

    names = [name]
    if is_wildcard(host):
        try:
            names += [info[4][0] for info in socket.getaddrinfo(socket.gethostname(), None)]
        except socket.gaierror:
            pass
    hosts = list(get_default_allowed_hosts())
    for n in names:
        netloc = f"[{n}]" if ":" in n else n
        hosts += [netloc, netloc.replace("[", "[[]", 1) + ":*"]
    return ",".join(dict.fromkeys(hosts))


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


def start(
    folder: Path,
    port: int,
    pg_port: int,
    workers: int,
    jobs: bool = False,
    host: str = "127.0.0.1",
    auth: bool = False,
    allowed: str | None = None,
) -> dict:
    """Start PostgreSQL and ``mlflow server`` on ``host``, with MLflow's basic-auth app if ``auth``; return the state
    written to ``folder/server.json``. A ``host`` that is not a loopback address is refused without ``auth``."""
    if not auth and not is_loopback(host):
        raise ServerError(
            f"--host {host} is not a loopback address: without authentication anyone who can reach "
            f"port {port} there could read, change and delete every run. Add --auth to turn on MLflow's "
            "basic-auth app (admin password generated into DIR/auth.password), or serve on 127.0.0.1"
        )
    if auth and importlib.util.find_spec("flask_wtf") is None:
        raise ServerError(
            "--auth needs MLflow's auth extra (Flask-WTF, for the app's CSRF checks): pip install 'mlflow[auth]'"
        )
    folder = folder.resolve()
    if (folder / STATE).exists():
        state = json.loads((folder / STATE).read_text())
        if alive(state["mlflow_pid"]):
            raise ServerError(f"already running from {folder}: {state['tracking_uri']} (stop it first)")
    folder.mkdir(parents=True, exist_ok=True)
    password = init_cluster(folder, pg_port)
    start_postgres(folder, pg_port)
    log = folder / "mlflow.log"
    name = socket.gethostname() if is_wildcard(host) else host
    netloc = f"[{name}]" if ":" in name else name  # an IPv6 address
    url = f"http://{netloc}:{port}"
    local = f"http://127.0.0.1:{port}" if is_wildcard(host) else url  # where this machine checks its health
    mlflow = Path(sys.executable).with_name("mlflow")
    cmd = [
        str(mlflow) if mlflow.exists() else "mlflow",
        "server",
        "--backend-store-uri",
        f"postgresql+psycopg://{PG_USER}@127.0.0.1:{pg_port}/{PG_DB}",
        "--artifacts-destination",
        str(folder / "artifacts"),
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        str(workers),
    ]
    if allowed or not is_loopback(host):
        cmd += ["--allowed-hosts", allowed or allowed_hosts(host, name)]
    # The password reaches psycopg through libpq's PGPASSWORD, not the command line. MLflow's server-side job runner
    # (huey consumers for its GenAI features; MLFLOW_SERVER_ENABLE_JOB_EXECUTION, on by default) is off unless asked
    # for: tracking never uses it, and it adds seven processes.
    env = {**os.environ, "PGPASSWORD": password, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "true" if jobs else "false"}
    if auth:  # the admin password and session key reach the app through its environment, like PGPASSWORD
        env.update(auth_setup(folder, pg_port, password))
        cmd += ["--app-name", "basic-auth"]
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, env=env)
    state = {
        "tracking_uri": url,
        "mlflow_pid": proc.pid,
        "port": port,
        "pg_port": pg_port,
        "host": host,
        "pgdata": str(folder / "pgdata"),
        "artifacts": str(folder / "artifacts"),
        "auth": {"username": AUTH_USER, "password_file": str(folder / AUTH_PASSWORD)} if auth else None,
    }
    (folder / STATE).write_text(json.dumps(state, indent=1))
    try:
        wait_healthy(local, proc, log)
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
    parser.add_argument("--port", type=int, default=5000, help="mlflow server's port")
    parser.add_argument(
        "--host", default="127.0.0.1", help="address mlflow server listens on; one that is not loopback needs --auth"
    )
    parser.add_argument(
        "--auth",
        action="store_true",
        help="serve MLflow's basic-auth app (admin password generated into DIR/auth.password)",
    )
    parser.add_argument(
        "--allowed-hosts",
        help="Host headers mlflow server answers (default: localhost, private addresses and the name start prints)",
    )
    parser.add_argument("--pg-port", type=int, default=5433, help="PostgreSQL's port on 127.0.0.1")
    parser.add_argument("--workers", type=int, default=2, help="mlflow server's worker processes")
    parser.add_argument("--jobs", action="store_true", help="start MLflow's server-side job runner too")
    args = parser.parse_args(argv)
    try:
        if args.action == "start":
            state = start(
                args.dir, args.port, args.pg_port, args.workers, args.jobs, args.host, args.auth, args.allowed_hosts
            )
            print(f"export MLFLOW_TRACKING_URI={state['tracking_uri']}")
            if state["auth"]:  # the password file's path, never the password
                print(f"export MLFLOW_TRACKING_USERNAME={state['auth']['username']}")
                print(f'export MLFLOW_TRACKING_PASSWORD="$(cat {state["auth"]["password_file"]})"')
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
