"""Real servers for the fleet tests and benchmark: a throw-away PostgreSQL cluster and a
moto S3 server (``tests/test_fleet_*.py``, ``bench/bench_fleet.py``).

**PostgreSQL** (Debian's ``postgresql`` package, installed by ``make test``): ``initdb``
in a fresh temporary directory, ``postgres`` listening on 127.0.0.1 only (a free
port) and on a unix socket inside that directory, trust authentication for the one
role ``lfcal``; stopped (``pg_ctl stop -m immediate``) and deleted at the end.
PostgreSQL's server refuses to run as root: when the tests run as root (CI), the
cluster's directory is given to the unprivileged user ``nobody`` and ``initdb`` /
``pg_ctl`` run as that user through ``setpriv`` (util-linux), so no user is created.

**S3**: moto's standalone server (``moto[server]`` from PyPI) in a thread of the test
process, bound to 127.0.0.1 on a free port. :meth:`S3Server.stop` shuts the HTTP
server down (connections are refused, as in an outage) while moto keeps the
buckets in memory; :meth:`S3Server.start` brings it back on the same port.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

S3_KEY_ID = "testing-key-id"
S3_SECRET = "testing-secret-key"
S3_REGION = "us-east-1"


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def pg_bin_dir() -> Path | None:
    """Debian's PostgreSQL server binaries (newest version), or None when not installed."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=_version_key)
    return Path(found[-1]).parent if found else None


def _version_key(path: str) -> float:
    try:
        return float(Path(path).parent.parent.name)
    except ValueError:
        return 0.0


class PostgresServer:
    """A running throw-away PostgreSQL cluster (see the module docstring)."""

    def __init__(self, bin_dir: Path, *, durable: bool = False) -> None:
        self.bin_dir = bin_dir
        self.durable = durable
        self.root = Path(tempfile.mkdtemp(prefix="lfcal-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.user = "lfcal"
        self._run_as: list[str] = []
        if os.geteuid() == 0:  # the server refuses root: run it as nobody
            nobody = pwd.getpwnam("nobody")
            os.chown(self.root, nobody.pw_uid, nobody.pw_gid)
            self._run_as = [
                "setpriv",
                f"--reuid={nobody.pw_uid}",
                f"--regid={nobody.pw_gid}",
                "--clear-groups",
                "--",
            ]
        os.chmod(self.root, 0o700)

    def _run(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "LC_ALL": "C", "TZ": "UTC"}
        return subprocess.run(
            [*self._run_as, *args],
            env=env,
            cwd=self.root,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=True,
        )

    def start(self) -> PostgresServer:
        self._run(
            str(self.bin_dir / "initdb"),
            "-D",
            str(self.data),
            "-U",
            self.user,
            "--auth=trust",
            "--no-sync",
            "-E",
            "UTF8",
        )
        fast = "" if self.durable else "-c fsync=off -c full_page_writes=off "
        options = (
            f"-c listen_addresses=127.0.0.1 -c port={self.port} "
            f"-c unix_socket_directories={self.root} {fast}"
            "-c max_connections=100 -c shared_buffers=16MB"
        )
        self._run(
            str(self.bin_dir / "pg_ctl"),
            "-D",
            str(self.data),
            "-o",
            options,
            "-l",
            str(self.root / "server.log"),
            "-w",
            "-t",
            "60",
            "start",
        )
        return self

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{self.user}@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        """A new empty database; returns its URL."""
        import psycopg

        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        try:
            self._run(str(self.bin_dir / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "stop")
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired):
            pass
        shutil.rmtree(self.root, ignore_errors=True)

    def log(self) -> str:
        try:
            return (self.root / "server.log").read_text(errors="replace")
        except OSError:
            return ""


@contextmanager
def postgres_server(*, durable: bool = False) -> Iterator[PostgresServer]:
    """A started cluster, stopped and deleted afterwards. ``durable``: fsync on (as a
    production server; the tests run it off, for speed)."""
    bin_dir = pg_bin_dir()
    if bin_dir is None:
        raise RuntimeError(
            "PostgreSQL server binaries not found in /usr/lib/postgresql/*/bin: install the "
            "Debian package postgresql (make setup does)"
        )
    server = PostgresServer(bin_dir, durable=durable)
    try:
        server.start()
    except subprocess.CalledProcessError as exc:
        log = server.log()
        server.stop()
        raise RuntimeError(f"PostgreSQL did not start: {exc.stderr}\n{log}") from exc
    try:
        yield server
    finally:
        server.stop()


def take_station_lock(admin: Any, station_id: str) -> None:
    """End the session holding ``station_id``'s ownership lock (as a database restart
    would) and take that lock on ``admin`` (an autocommit psycopg connection), as
    another process with the same station id would. ``pg_advisory_unlock`` gives it back.
    """
    from station.ownership import OWNERSHIP_KEY

    row = admin.execute(
        "SELECT pid FROM pg_locks WHERE locktype = 'advisory' AND classid = %s "
        "AND objid = hashtext(%s)::oid AND objsubid = 2",
        (OWNERSHIP_KEY, station_id),
    ).fetchone()
    if row is not None:
        admin.execute("SELECT pg_terminate_backend(%s)", (row[0],))
    admin.execute("SELECT pg_advisory_lock(%s, hashtext(%s))", (OWNERSHIP_KEY, station_id))


def give_station_lock_back(admin: Any, station_id: str) -> None:
    """Release the lock :func:`take_station_lock` took."""
    from station.ownership import OWNERSHIP_KEY

    admin.execute("SELECT pg_advisory_unlock(%s, hashtext(%s))", (OWNERSHIP_KEY, station_id))


class S3Server:
    """moto's S3 server on 127.0.0.1 (see the module docstring)."""

    def __init__(self) -> None:
        self.port = free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self._server: Any = None

    def start(self) -> S3Server:
        import logging

        from moto.server import ThreadedMotoServer

        logging.getLogger("werkzeug").setLevel(logging.ERROR)  # no line per request

        deadline = time.monotonic() + 20
        while True:
            try:
                server = ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
                server.start()
                break
            except OSError:  # the port of the previous run is still being released
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        self._server = server
        self._wait_listening()
        return self

    def _wait_listening(self) -> None:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                    return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError("the moto S3 server did not start listening")

    def stop(self) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None

    def env(self) -> dict[str, str]:
        """The usual AWS environment variables that point boto3 at this server."""
        return {
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_ACCESS_KEY_ID": S3_KEY_ID,
            "AWS_SECRET_ACCESS_KEY": S3_SECRET,
            "AWS_DEFAULT_REGION": S3_REGION,
        }

    def client(self) -> Any:
        import boto3

        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id=S3_KEY_ID,
            aws_secret_access_key=S3_SECRET,
            region_name=S3_REGION,
        )

    def create_bucket(self, name: str) -> None:
        self.client().create_bucket(Bucket=name)


@contextmanager
def s3_server() -> Iterator[S3Server]:
    server = S3Server().start()
    try:
        yield server
    finally:
        server.stop()
