"""The lab's grids as campaign specs (the YAML files here, `tsr_koopman_ctrl.campaign.spec`) and
what each study does with its own: fly it through the product's campaign API into its
directory, on the engine its --workers or --address name."""

import os

HERE = os.path.dirname(os.path.abspath(__file__))


def spec_path(name):
    """The path of a spec here, by its name relative to this folder."""
    return os.path.join(HERE, name)


def add_engine_options(parser):
    """--workers N | --address ADDR: where a study's campaign flies."""
    engine = parser.add_mutually_exclusive_group()
    engine.add_argument('--workers', type=int, help='local Dask workers (default: one per core)')
    engine.add_argument('--address', help='a Dask scheduler to fly on instead (tcp://host:8786)')


def fly(campaign, out, workers=None, address=None):
    """The campaign's rows, flown into `out` (`run_campaign`), resumed where `out` holds it
    already: a finished one is read back, not flown; another campaign there is refused
    (ValueError, one line)."""
    from tsr_koopman_ctrl.campaign import run_campaign
    resume = os.path.exists(os.path.join(out, 'spec.yaml'))
    return run_campaign(campaign, out, workers=workers, address=address, resume=resume)
