"""How every study leaves its results: <name>.json and <name>.md in its output directory, and
its table in the docs page that shows it (between markers)."""

import json
import os


def write_results(directory, name, data, text, indent=1):
    """<name>.json (`data`) and <name>.md (`text`) in `directory`, made if needed."""
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, f'{name}.json'), 'w') as f:
        json.dump(data, f, indent=indent)
    with open(os.path.join(directory, f'{name}.md'), 'w') as f:
        f.write(text)


def write_into_page(page, name, text):
    """Put `text` into the docs page `page` between its markers `<!-- name:begin -->` and
    `<!-- name:end -->` (ValueError if it has none), so the page shows what the study made."""
    begin, end = f'<!-- {name}:begin -->', f'<!-- {name}:end -->'
    with open(page) as f:
        content = f.read()
    if content.count(begin) != 1 or content.count(end) != 1 or \
            content.index(begin) > content.index(end):
        raise ValueError(f'{page} has no {begin} ... {end} markers for {name}')
    head, rest = content.split(begin)
    _, tail = rest.split(end)
    with open(page, 'w') as f:
        f.write(f'{head}{begin}\n{text.rstrip()}\n{end}{tail}')
