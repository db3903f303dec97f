"""A shared tracking server: MLflow on PostgreSQL, its artifacts served through it (``harness store serve``).

Many writers (a sweep's workers on several machines, Ray cells) at once are more than a SQLite file
takes well; this starts the store that does::

    DIR/postgres/          the PostgreSQL cluster (initialised on the first start), DIR/postgres.log its log
    DIR/artifacts/         every run's files; clients reach them through the server (no shared path)
    DIR/mlflow-server.log  the MLflow server's log

PostgreSQL listens on 127.0.0.1 only, with ``trust`` authentication (anyone on this machine may
connect); the MLflow server listens where ``--host`` says. PostgreSQL refuses to run as root: run as
root, the cluster is owned by and run as the user ``postgres`` (who must be able to reach DIR).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from harness.errors import TrackingError

#: the cluster's superuser and the database MLflow keeps its records in
DB_USER = "harness"
DB_NAME = "mlflow"
#: the unprivileged user PostgreSQL runs as when the harness runs as root
ROOT_RUNS_POSTGRES_AS = "postgres"


class ServerPaths:
    """Where a served store keeps its parts, all under ``directory``."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self.cluster = self.directory / "postgres"
        self.postgres_log = self.directory / "postgres.log"
        self.artifacts = self.directory / "artifacts"
        self.mlflow_log = self.directory / "mlflow-server.log"


def backend_uri(db_port: int) -> str:
    return f"postgresql+psycopg2://{DB_USER}@127.0.0.1:{db_port}/{DB_NAME}"


def tracking_uri(host: str, port: int) -> str:
    return f"http://{host}:{port}"


def serve_command(directory: Path) -> str:
    return f"harness store serve --dir {directory}"


def _binary(name: str) -> str:
    found = shutil.which(name)
    if found is None:
        raise TrackingError(f"PostgreSQL's {name} is not on PATH; install PostgreSQL (e.g. apt-get install postgresql, "
                            "then add /usr/lib/postgresql/<version>/bin to PATH) to serve a store")
    return found


def postgres_available() -> bool:
    """Whether PostgreSQL's binaries (initdb, pg_ctl, postgres) are on PATH."""
    return all(shutil.which(n) for n in ("initdb", "pg_ctl", "postgres"))


def check_port_free(host: str, port: int, what: str, option: str) -> None:
    """A :class:`TrackingError` naming ``what`` and ``option`` if something listens on ``host:port``."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            raise TrackingError(f"port {port} on {host} ({what}) is busy; pass another with {option}") from None


def _as_owner(command: list[str]) -> list[str]:
    """``command`` run as the cluster's owner: this user, or ``postgres`` when this is root (PostgreSQL refuses root)."""
    if os.geteuid() != 0:
        return command
    return ["runuser", "-u", ROOT_RUNS_POSTGRES_AS, "--", *command]


def _prepare_for_owner(paths: ServerPaths) -> None:
    """As root, hand the cluster's folder and log to ``postgres``; a :class:`TrackingError` if it cannot reach them."""
    if os.geteuid() != 0:
        return
    import pwd

    try:
        owner = pwd.getpwnam(ROOT_RUNS_POSTGRES_AS)
    except KeyError:
        raise TrackingError(f"PostgreSQL refuses to run as root and there is no user {ROOT_RUNS_POSTGRES_AS!r} to run it as; "
                            f"run `{serve_command(paths.directory)}` as a non-root user") from None
    paths.cluster.mkdir(mode=0o700, exist_ok=True)
    paths.postgres_log.touch()
    for path in (paths.cluster, paths.postgres_log):
        os.chown(path, owner.pw_uid, owner.pw_gid)
    reachable = subprocess.run(_as_owner(["test", "-w", str(paths.cluster)]), capture_output=True).returncode == 0
    if not reachable:
        raise TrackingError(f"PostgreSQL runs as user {ROOT_RUNS_POSTGRES_AS!r} here (not as root), who cannot reach {paths.cluster}; "
                            f"serve from a directory every user can traverse (e.g. under /tmp or /srv) or run as a non-root user")


def _run(command: list[str], what: str, log: Path | None = None) -> None:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        detail = (done.stderr or done.stdout).strip().splitlines()
        where = f" (log: {log})" if log is not None else ""
        raise TrackingError(f"{what} failed: {detail[-1] if detail else f'exit {done.returncode}'}{where}")


def init_cluster(paths: ServerPaths) -> bool:
    """Initialise the PostgreSQL cluster in ``paths.cluster`` unless there is one; whether it was created."""
    if (paths.cluster / "PG_VERSION").exists():
        return False
    paths.directory.mkdir(parents=True, exist_ok=True)
    _prepare_for_owner(paths)
    _run(_as_owner([_binary("initdb"), "-D", str(paths.cluster), "-U", DB_USER, "--auth=trust", "-E", "UTF8", "--no-instructions"]),
         f"initdb of {paths.cluster}")
    return True


def start_postgres(paths: ServerPaths, db_port: int) -> None:
    """Start the cluster on ``127.0.0.1:db_port`` (its socket in the cluster's folder) and wait until it accepts connections."""
    _prepare_for_owner(paths)
    options = f"-p {db_port} -k {paths.cluster} -c listen_addresses=127.0.0.1"
    _run(_as_owner([_binary("pg_ctl"), "-D", str(paths.cluster), "-l", str(paths.postgres_log), "-o", options, "-w", "-t", "60", "start"]),
         f"starting PostgreSQL of the store {paths.directory}", paths.postgres_log)


def postgres_running(paths: ServerPaths) -> bool:
    """Whether the cluster's postmaster (the pid in ``postmaster.pid``) is alive."""
    try:
        pid = int((paths.cluster / "postmaster.pid").read_text().split()[0])
        os.kill(pid, 0)
    except (OSError, ValueError, IndexError):
        return False
    return True


def stop_postgres(paths: ServerPaths) -> None:
    """Stop the cluster (fast: open connections are closed, committed data kept); nothing if it is not running."""
    if postgres_running(paths):
        subprocess.run(_as_owner([_binary("pg_ctl"), "-D", str(paths.cluster), "-m", "fast", "-w", "stop"]), capture_output=True)


def ensure_database(db_port: int) -> None:
    """Create the database :data:`DB_NAME` if the cluster has none of that name."""
    try:
        import psycopg2
    except ImportError:
        raise TrackingError("the PostgreSQL driver is missing; pip install 'pilco-harness[server]' (psycopg2-binary)") from None
    connection = psycopg2.connect(host="127.0.0.1", port=db_port, user=DB_USER, dbname="postgres")
    try:
        connection.autocommit = True
        with connection.cursor() as cursor:
            cursor.execute("SELECT 1 FROM pg_database WHERE datname = %s", (DB_NAME,))
            if cursor.fetchone() is None:
                cursor.execute(f'CREATE DATABASE "{DB_NAME}"')
    finally:
        connection.close()


def start_mlflow(paths: ServerPaths, host: str, port: int, db_port: int, workers: int) -> subprocess.Popen:
    """``mlflow server`` on the cluster, serving the artifacts of ``paths.artifacts``, in its own session (log: ``paths.mlflow_log``)."""
    paths.artifacts.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", backend_uri(db_port),
               "--serve-artifacts", "--artifacts-destination", str(paths.artifacts.resolve()),
               "--host", host, "--port", str(port), "--workers", str(workers)]
    with open(paths.mlflow_log, "a") as log:
        return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def answers(uri: str) -> bool:
    """Whether the MLflow server at ``uri`` answers its health check."""
    try:
        with urllib.request.urlopen(f"{uri}/health", timeout=2) as response:
            return response.status == 200
    except OSError:
        return False


def wait_until_answers(uri: str, process: subprocess.Popen, paths: ServerPaths, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise TrackingError(f"the MLflow server of the store {paths.directory} ended at its start (exit {process.returncode}); "
                                f"see {paths.mlflow_log}")
        if answers(uri):
            return
        time.sleep(0.5)
    raise TrackingError(f"the MLflow server at {uri} did not answer within {timeout:.0f} s; see {paths.mlflow_log}")


def stop_process(process: subprocess.Popen, timeout: float = 20) -> None:
    """SIGTERM to the process's group (the server and its workers), SIGKILL if it has not ended within ``timeout`` s."""
    import signal

    if process.poll() is not None:
        return
    for signum, wait in ((signal.SIGTERM, timeout), (signal.SIGKILL, 5)):
        try:
            os.killpg(process.pid, signum)
        except ProcessLookupError:
            return
        try:
            process.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


class StoreServer:
    """A store served from ``directory``: PostgreSQL on ``db_port`` and MLflow on ``host:port``.

    ``start()`` initialises the cluster if absent, starts PostgreSQL, creates the database, starts the
    MLflow server and waits until it answers; ``stop()`` stops both (MLflow first). A context manager.
    """

    def __init__(self, directory: Path, port: int = 5000, db_port: int = 5432, host: str = "127.0.0.1",
                 workers: int = 2, timeout: float = 120) -> None:
        self.paths = ServerPaths(Path(directory).resolve())
        self.port, self.db_port, self.host, self.workers, self.timeout = port, db_port, host, workers, timeout
        self.mlflow: subprocess.Popen | None = None
        self._postgres_started = False

    @property
    def uri(self) -> str:
        return tracking_uri(self.host, self.port)

    def start(self) -> StoreServer:
        for name in ("initdb", "pg_ctl", "postgres"):
            _binary(name)
        check_port_free(self.host, self.port, "the MLflow server", "--port")
        check_port_free("127.0.0.1", self.db_port, "PostgreSQL", "--db-port")
        try:
            init_cluster(self.paths)
            start_postgres(self.paths, self.db_port)
            self._postgres_started = True
            ensure_database(self.db_port)
            self.mlflow = start_mlflow(self.paths, self.host, self.port, self.db_port, self.workers)
            wait_until_answers(self.uri, self.mlflow, self.paths, self.timeout)
        except BaseException:
            self.stop()
            raise
        return self

    def problem(self) -> str | None:
        """What has stopped of the two (a one-line error naming the store and the fix), else ``None``."""
        if not postgres_running(self.paths):
            return (f"PostgreSQL of the store {self.paths.directory} stopped (log: {self.paths.postgres_log}); "
                    f"restart the store with `{serve_command(self.paths.directory)} --port {self.port} --db-port {self.db_port}`")
        if self.mlflow is not None and self.mlflow.poll() is not None:
            return (f"the MLflow server of the store {self.paths.directory} ended (exit {self.mlflow.returncode}; "
                    f"log: {self.paths.mlflow_log}); restart it with `{serve_command(self.paths.directory)}`")
        return None

    def stop(self) -> None:
        if self.mlflow is not None:
            stop_process(self.mlflow)
            self.mlflow = None
        if self._postgres_started:
            stop_postgres(self.paths)
            self._postgres_started = False

    def __enter__(self) -> StoreServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
