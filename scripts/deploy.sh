#!/usr/bin/env bash
# Main job: closed-loop TSR deployment over DDS (simulator, controller, recorder as three
# processes). Sets everything up on first use. Extra arguments go to tsr_koopman_ctrl.deploy
# (--help lists them).
set -eo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/setup.sh
exec python -m tsr_koopman_ctrl.commands.deploy "$@"
