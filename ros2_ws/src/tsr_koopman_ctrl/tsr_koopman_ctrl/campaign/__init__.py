"""Monte Carlo campaigns, ROS-free: dispersed runs of one or more laws on Dask distributed, each
row kept as it ends, a report with success rates and their confidence bounds.

    from tsr_koopman_ctrl.campaign import load_spec, run_campaign, report
    campaign = load_spec('spec.yaml', runs=200)     # or Campaign.parse({...}); spec.py: the spec
    rows = run_campaign(campaign, 'out/campaign')   # a local cluster, one worker per core
    report('out/campaign')                          # out/campaign/report.md and its figures
    row, stored = replay('out/campaign', 17, 'koopman_nmpc')   # run 17 again, here

The command: `python -m tsr_koopman_ctrl.commands.campaign` (docs/campaign.md).
"""

from tsr_koopman_ctrl.campaign.engine import (CampaignError, differences, fly,  # noqa: F401
                                              replay, run_campaign)
from tsr_koopman_ctrl.campaign.report import clopper_pearson  # noqa: F401
from tsr_koopman_ctrl.campaign.report import write_report as report  # noqa: F401
from tsr_koopman_ctrl.campaign.rows import read_rows  # noqa: F401
from tsr_koopman_ctrl.campaign.spec import Campaign, load_spec  # noqa: F401
