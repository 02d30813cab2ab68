"""How every study leaves its results: <name>.json and <name>.md in its output directory."""

import json
import os


def write_results(directory, name, data, text, indent=1):
    """<name>.json (`data`) and <name>.md (`text`) in `directory`, made if needed."""
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, f'{name}.json'), 'w') as f:
        json.dump(data, f, indent=indent)
    with open(os.path.join(directory, f'{name}.md'), 'w') as f:
        f.write(text)
