"""The recorder node's parameters, declared once as a schema class (`tsr_sim.schema`),
ROS-free."""

import dataclasses

from tsr_sim.schema import LIVE, setting, Settings
from tsr_sim.wire import LOOP_TOPIC_TYPES

DEFAULT_TOPICS = tuple(LOOP_TOPIC_TYPES)
DEFAULT_TYPES = tuple(LOOP_TOPIC_TYPES.values())


@dataclasses.dataclass(frozen=True)
class RecorderNodeSettings(Settings):
    """What to record, where, and how the bag is written: the bag's shape is read at start,
    its splitting, flushing and the node's watching are applied when set."""

    topics: tuple = setting(DEFAULT_TOPICS, "topics to record (relative names resolve in the "
                            "node's namespace)", fixed_length=False)
    #: With topics other than the default ones the node's default is [''] (all discovered).
    types: tuple = setting(DEFAULT_TYPES, 'message type of each topic (pkg/msg/Type), '
                           "subscribed at start so nothing is missed; '' or a shorter list: "
                           'discovered from publishers', fixed_length=False)
    output_dir: str = setting('bags', 'directory the bag is created in')
    bag_name: str = setting('', 'bag directory name (empty: tsr_<UTC time to the '
                            'microsecond>_<random hex>, a directory not there yet)')
    max_file_size: int = setting(0, 'split after this many bytes (0: never)', low=0,
                                 high=2 ** 62, applied=LIVE)
    max_file_duration: float = setting(0.0, 'split after this many seconds (0: never)',
                                       low=0.0, high=1e9, applied=LIVE)
    chunk_size: int = setting(1 << 20, 'MCAP chunk size in bytes (a chunk is also closed every '
                              'flush_period)', low=256, high=1 << 30)
    flush_period: float = setting(1.0, 'seconds: a chunk in progress is written out at least '
                                  'this often, so a kill -9 loses at most about this much (0: '
                                  'only by chunk size)', low=0.0, high=3600.0, applied=LIVE)
    silence_warning: float = setting(5.0, 'seconds: warn once per topic when publishers are '
                                     'matched but no message has arrived for this long (0: '
                                     'never)', low=0.0, high=3600.0, applied=LIVE)
    discovery_period: float = setting(0.2, 'seconds between looks for new topics', low=0.01,
                                      high=60.0, applied=LIVE)
