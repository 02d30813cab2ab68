"""Bags, ROS-free: the rosbag2-layout MCAP writer and reader, and the TSR loop read back.

    from tsr_koopman_ctrl.bag import BagReader, read_loop
    loop = read_loop('bags/deploy_...')          # states, tensions, statuses, compute times
    runs = read_runs('bags/reset_...')           # one RecordedLoop per run (a reset between)
    runs = read_runs('bags/hw', scale=Scale(mass=35.0), sample_period=10.0)   # no RunInfo
    print(loop.report.summary())                 # one line per file: complete, truncated, ...

A bag a crash left open: `recover(BAG)` (`bag.files`; the command: `python -m
tsr_koopman_ctrl.commands.bag recover BAG`).
"""

from tsr_koopman_ctrl.bag.definitions import TopicInfo  # noqa: F401
from tsr_koopman_ctrl.bag.files import info, recover, runs  # noqa: F401
from tsr_koopman_ctrl.bag.reader import BagReader, FileReport, ReadReport  # noqa: F401
from tsr_koopman_ctrl.bag.tsr_loop import (BagWarning, read_loop, read_runs,  # noqa: F401
                                           RecordedLoop)
from tsr_koopman_ctrl.bag.writer import BagWriter  # noqa: F401
