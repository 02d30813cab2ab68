"""Start the project's nodes as separate processes (there is no ros2 launch in the wheel set-up).

ROS-free: it finds `<prefix>/lib/<pkg>/<exe>` through the ament index, exactly where `ros2 run`
looks on a stock install, writes the parameters to a YAML `--params-file` and manages the process.
Used by the main job, the comparison runs and the integration tests.
"""

import atexit
import contextlib
import os
import random
import signal
import subprocess
import tempfile

from ament_index_python.packages import get_package_prefix
import yaml


def executable(package, name):
    path = os.path.join(get_package_prefix(package), 'lib', package, name)
    if not os.access(path, os.X_OK):
        raise FileNotFoundError(f'{package} {name}: no executable at {path}; build the workspace')
    return path


def write_params(node_name, params, directory):
    """Write `params` for node `node_name` as a ROS 2 parameter file; return its path."""
    path = os.path.join(directory, f'{node_name}.params.yaml')
    with open(path, 'w') as f:
        yaml.safe_dump({'/**': {'ros__parameters': params}}, f)
    return path


#: The domains a run picks when none is given. DDS's ports for domain d start at 7400 + 250 d;
#: past 101 they reach Linux's ephemeral range (32768..60999), where the kernel hands ports to
#: client sockets, so a participant could find its port taken (the ROS 2 docs, "The
#: ROS_DOMAIN_ID", advise 0..101). 0 is every ROS graph's default, so it is left out too.
FREE_DOMAIN_IDS = range(1, 102)

#: The lock files by which this project's processes reserve a domain (one per domain, flock).
DOMAIN_LOCKS = os.path.join(tempfile.gettempdir(), 'tsr-dds-domains')


def domain_ports(domain):
    """The UDP ports DDS gives `domain` (DDSI-RTPS 2.5, 9.6.1.1): port base 7400, domain gain
    250; every participant's discovery and user ports (offsets 0, 1, 10 + 2 p, 11 + 2 p) lie
    in these 250."""
    return range(7400 + 250 * domain, 7400 + 250 * (domain + 1))


def bound_udp_ports():
    """The UDP ports bound on this host (every process, IPv4 and IPv6), from /proc/net; None
    where the system has no such table."""
    ports, found = set(), False
    for table in ('/proc/net/udp', '/proc/net/udp6'):
        try:
            with open(table) as f:
                rows = f.read().splitlines()[1:]
        except OSError:
            continue
        found = True
        ports.update(int(row.split()[1].rpartition(':')[2], 16) for row in rows if row.strip())
    return ports if found else None


def port_bound(port):
    """Whether a UDP port is bound here: a bind without SO_REUSEADDR fails where a DDS
    participant's socket (which sets it) holds the port. Where /proc/net is not readable."""
    import socket
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind(('', port))
    except OSError:
        return True
    finally:
        probe.close()
    return False


def domain_in_use(domain, bound=None):
    """Whether a DDS participant (of any program, this project's or not) is on `domain` on
    this host: one of the domain's UDP ports is bound. `bound`: bound_udp_ports(), read once
    for many domains."""
    if bound is None:
        bound = bound_udp_ports()
    if bound is None:      # no /proc/net: the discovery multicast port, which every
        return port_bound(domain_ports(domain)[0])     # participant binds by default
    ports = domain_ports(domain)
    return any(port in ports for port in bound)


class DomainReservation:
    """A DDS domain this process reserved (`reserve_domain`): its lock is held until
    release(), the end of a `with` block, or the end of the process."""

    def __init__(self, domain, fd):
        self.id, self._fd = domain, fd

    def release(self):
        if self._fd is not None:
            os.close(self._fd)      # closing the file drops its flock
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()

    def __del__(self):
        self.release()

    def __repr__(self):
        return f'DomainReservation({self.id})'


def _lock(domain, lock_dir):
    """The file descriptor of `domain`'s lock file, locked; None if another process holds it.
    The directory is shared (sticky, writable by all, like /tmp) so that every user's runs
    see each other's locks; a lock file another user made is locked read-only."""
    import fcntl
    if not os.path.isdir(lock_dir):
        os.makedirs(lock_dir, exist_ok=True)
        with contextlib.suppress(OSError):
            os.chmod(lock_dir, 0o1777)
    fd = os.open(os.path.join(lock_dir, f'{domain}.lock'), os.O_RDONLY | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def reserve_domain(rng=random, candidates=FREE_DOMAIN_IDS, lock_dir=None):
    """A DDS domain no other process on this host uses, reserved for the caller: the first, in
    a random order, of `candidates` that is not the caller's ROS_DOMAIN_ID (a graph the user
    may be running), whose UDP ports no process has bound (`domain_in_use`: any DDS program,
    leftovers of earlier runs too) and whose lock file (under DOMAIN_LOCKS) no other process
    of this project holds. Both checks: the ports see every program but only once its
    participants are up; the lock is taken at once, before any process starts, so two draws
    at the same moment never collide. RuntimeError if every candidate is taken."""
    lock_dir = lock_dir or DOMAIN_LOCKS
    try:
        taken = int(os.environ.get('ROS_DOMAIN_ID', ''))
    except ValueError:      # unset, empty or not a number: rcl's default, 0, which is left out
        taken = None
    order = [d for d in candidates if d != taken]
    rng.shuffle(order)
    bound = bound_udp_ports()
    for domain in order:
        if domain_in_use(domain, bound):
            continue
        fd = _lock(domain, lock_dir)
        if fd is not None:
            return DomainReservation(domain, fd)
    raise RuntimeError(f'no free DDS domain: all of {len(order)} candidates are in use on '
                       'this host (bound UDP ports or held locks)')


#: The reservations random_domain_id made: held for the rest of the process.
_KEPT = []


def random_domain_id(rng=random):
    """A free domain of its own for a run (`reserve_domain`), reserved for the rest of this
    process. Prefer reserve_domain, whose reservation can be released."""
    reservation = reserve_domain(rng)
    _KEPT.append(reservation)
    return reservation.id


#: One BLAS / OpenMP thread for every process a tool starts, unless the caller chose: processes
#: on this project's few cores each spinning several OpenBLAS threads stall one another. Two
#: `koopman_nmpc` loops side by side ran 0.93 s a step with numpy's default threads against
#: 0.18 with one (one alone: 0.17 and 0.15; 2 cores).
ONE_THREAD = {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1'}


def child_environment(extra=None):
    """os.environ with ONE_THREAD where the caller set none of its variables, plus `extra`."""
    environment = dict(os.environ)
    if not any(name in environment for name in ONE_THREAD):
        environment.update(ONE_THREAD)
    return dict(environment, **(extra or {}))


@contextlib.contextmanager
def one_thread_children():
    """Within: os.environ with ONE_THREAD as child_environment() adds it, for children that
    take os.environ as it is when they start (a spawn pool); the caller's variables after."""
    added = {name: value for name, value in child_environment().items()
             if name not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for name in added:
            os.environ.pop(name, None)


#: Every NodeProcess not yet stopped: killed at the interpreter's exit (`_kill_survivors`), so
#: that no node outlives the tool or the test that started it, whatever path it left by.
_LIVE = set()


@atexit.register
def _kill_survivors():
    for process in list(_LIVE):
        process.kill()


class NodeProcess:
    """One node in its own process; stop() sends SIGINT, then SIGKILL after a grace period."""

    def __init__(self, package, exe, node_name, params=None, domain_id=None, log_path=None,
                 extra_args=(), namespace=None, cwd=None, env=None):
        self.name = node_name
        self.log_path = log_path
        self._tmp = tempfile.TemporaryDirectory(prefix=f'{node_name}-')
        self._log = None
        try:
            cmd = [executable(package, exe), '--ros-args', '-r', f'__node:={node_name}']
            if namespace:
                cmd += ['-r', f'__ns:={namespace}']
            if params:
                cmd += ['--params-file', write_params(node_name, params, self._tmp.name)]
            cmd += list(extra_args)
            environment = child_environment(env)   # env: extra variables
            if domain_id is not None:
                environment['ROS_DOMAIN_ID'] = str(domain_id)
            self._log = open(log_path, 'w') if log_path else None   # None: this console
            self.process = subprocess.Popen(cmd, env=environment, stdout=self._log,
                                            stderr=subprocess.STDOUT, cwd=cwd)
        except BaseException:
            self._close_files()
            raise
        _LIVE.add(self)

    def log_tail(self, lines=10):
        """The last lines of the node's log ('' when it logs to the console)."""
        if not self.log_path:
            return ''
        try:
            with open(self.log_path, errors='replace') as log:
                return ''.join(log.readlines()[-lines:])
        except OSError:
            return ''

    def running(self):
        return self.process.poll() is None

    def wait(self, timeout=None):
        return self.process.wait(timeout)

    def kill(self):
        """SIGKILL: no clean-up at all (what a crash looks like)."""
        self.process.kill()
        return self.process.wait()

    def stop(self, sig=signal.SIGINT, grace=10.0):
        """Ask the node to finish cleanly; kill it if it does not within `grace` seconds, or if
        the wait is cut short (an exception, a test's timeout, Ctrl-C): the process never
        outlives the call."""
        try:
            if self.running():
                self.process.send_signal(sig)
                try:
                    self.process.wait(grace)
                except subprocess.TimeoutExpired:
                    pass
        finally:
            if self.running():
                self.process.kill()
            self.process.wait()
            _LIVE.discard(self)
            self._close_files()
        return self.process.returncode

    def _close_files(self):
        if self._log is not None:
            self._log.close()
        self._tmp.cleanup()
