"""The training envelope of the shipped models: each model's sampled training data drawn again
from the provenance its model.json records, and the box of its states (`dataset.envelope`)
written into that model.json as `envelope` (the weights are untouched). `train` writes it for
every model it trains; this gives it to models trained before it did.

    python -m lab.model_envelopes [MODEL_DIR ...]      (default: every model under models/)
"""

import argparse
import json
import os
import sys

from tsr_koopman_ctrl.learning import dataset


def add_envelope(directory):
    path = os.path.join(directory, 'model.json')
    with open(path) as f:
        text = f.read()
    meta = json.loads(text)
    second = text.splitlines()[1]
    indent = len(second) - len(second.lstrip())     # as the file was written
    data = dataset.resample(meta['data']['train'])
    meta['envelope'] = dataset.envelope(data)
    with open(path, 'w') as f:
        f.write(json.dumps(meta, indent=indent) + '\n')
    return meta['envelope']


def main(argv=None):
    p = argparse.ArgumentParser(prog='model_envelopes', description=__doc__.split('\n\n')[0])
    p.add_argument('models', nargs='*')
    args = p.parse_args(argv)
    models = args.models or sorted(os.path.join('models', name) for name in os.listdir('models')
                                   if os.path.isfile(os.path.join('models', name, 'model.json')))
    for directory in models:
        try:
            box = add_envelope(directory)
        except (ValueError, KeyError) as error:
            print(f'{directory}: no envelope ({error})', file=sys.stderr)
            continue
        print(f"{directory}: low {[round(v, 3) for v in box['low']]}, high "
              f"{[round(v, 3) for v in box['high']]} ({box['states']} states)", flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
