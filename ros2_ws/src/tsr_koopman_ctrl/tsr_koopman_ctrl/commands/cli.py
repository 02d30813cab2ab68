"""The commands' argparse helpers: the generic types (`tsr_koopman_ctrl.arguments`) and the
options that read a bag of the loop."""

from tsr_sim import dynamics
from tsr_sim.units import DEFAULT_MASS, PAPER_ORBIT_RATE, PAPER_TETHER_LENGTH, Scale

# The generic types, by the names the commands use (their home: tsr_koopman_ctrl.arguments).
from tsr_koopman_ctrl.arguments import (add_overwrite, check_range, DOMAIN_ID,  # noqa: F401
                                        integer, INTERRUPTED_STATUS, model_dir, number,
                                        output_dir, SEED, STEPS, torch_device)


def add_loop_reading(parser):
    """The options that read a bag the simulator did not describe (no RunInfo: hardware's, or
    another recorder's): its units, its sample period, how its commands apply. A bag with the
    simulator's RunInfo is read with the simulator's own units and period."""
    group = parser.add_argument_group(
        'bags without a simulator RunInfo (hardware, another recorder)',
        'A bag needs only tsr/state and tsr/tension_cmd. Units and sample period come from '
        "the simulator's RunInfo when the bag has one, else from these options.")
    from tsr_koopman_ctrl.bag.tsr_loop import GIVEN_PERIOD_TOLERANCE
    paper_h = Scale().tau_to_seconds(dynamics.PAPER_STEP)
    group.add_argument('--sample-period', type=number(above=0), metavar='SECONDS',
                       help="sample period (default: the median interval of the states' "
                       'header stamps per step); retrain takes it for the model\'s within a '
                       f'relative {GIVEN_PERIOD_TOLERANCE:g}: the paper\'s 0.01 tau is '
                       f'{paper_h:.6g} s at the default orbit rate ({paper_h:.4g} passes too)')
    group.add_argument('--orbit-rate', type=number(above=0), metavar='RAD_PER_S',
                       help=f"orbit rate Omega (default: the paper's {PAPER_ORBIT_RATE:g})")
    group.add_argument('--tether-length', type=number(above=0), metavar='METRES',
                       help=f"full tether length L (default: the paper's {PAPER_TETHER_LENGTH:g})")
    group.add_argument('--mass', type=number(above=0), metavar='KG',
                       help=f'robot mass m (default: {DEFAULT_MASS:g}, the paper gives none)')
    group.add_argument('--match-commands', choices=('step', 'time'),
                       help="how a command applies: 'step', to the state whose step it carries "
                       "(a lockstep simulator); 'time', from when it was received until the "
                       "next command (zero-order hold: a timed simulator, hardware). Default: "
                       "'step' if the simulator's RunInfo says lockstep, else 'time'")


def loop_reading(args):
    """The options `add_loop_reading` added, as `bag.read_runs` takes them."""
    from tsr_koopman_ctrl.bag.tsr_loop import reading_options
    return reading_options(args.sample_period, args.orbit_rate, args.tether_length, args.mass,
                           args.match_commands)
