"""Start the project's nodes as separate processes (there is no ros2 launch in the wheel set-up).

ROS-free: it finds `<prefix>/lib/<pkg>/<exe>` through the ament index, exactly where `ros2 run`
looks on a stock install, writes the parameters to a YAML `--params-file` and manages the process.
Used by the main job, the comparison runs and the integration tests.
"""

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


def random_domain_id(rng=random):
    """A domain of its own for a run: one of FREE_DOMAIN_IDS, not the caller's ROS_DOMAIN_ID
    (a graph the user may be running)."""
    try:
        taken = int(os.environ.get('ROS_DOMAIN_ID', ''))
    except ValueError:      # unset, empty or not a number: rcl's default, 0, which is left out
        taken = None
    return rng.choice([d for d in FREE_DOMAIN_IDS if d != taken])


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


class NodeProcess:
    """One node in its own process; stop() sends SIGINT, then SIGKILL after a grace period."""

    def __init__(self, package, exe, node_name, params=None, domain_id=None, log_path=None,
                 extra_args=(), namespace=None, cwd=None, env=None):
        self.name = node_name
        self.log_path = log_path
        self._tmp = tempfile.TemporaryDirectory(prefix=f'{node_name}-')
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
        """Ask the node to finish cleanly; kill it if it does not within `grace` seconds."""
        if self.running():
            self.process.send_signal(sig)
            try:
                self.process.wait(grace)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self._log is not None:
            self._log.close()
        self._tmp.cleanup()
        return self.process.returncode
