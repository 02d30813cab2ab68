"""How every study leaves its results: <name>.json and <name>.md in its output directory, and
its table in the docs page that shows it (between markers)."""

import datetime
import json
import os
import shutil


def write_results(directory, name, data, text, indent=1):
    """<name>.json (`data`) and <name>.md (`text`) in `directory`, made if needed."""
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, f'{name}.json'), 'w') as f:
        json.dump(data, f, indent=indent)
    with open(os.path.join(directory, f'{name}.md'), 'w') as f:
        f.write(text)


def publish(directory, name, data, text, page=None, indent=1, marker=None):
    """A study's ending: its results written (`write_results`), its table put into `page`
    between the markers `marker` (default `name`) if a page is given (`write_into_page`), and
    printed."""
    write_results(directory, name, data, text, indent)
    if page:
        write_into_page(page, marker or name, text)
    print(text)


def check_page(page, name):
    """ValueError (one line) unless `page` has the markers of `name`: a study checks before its
    work, so that a long run is not lost at the end."""
    begin, end = f'<!-- {name}:begin -->', f'<!-- {name}:end -->'
    try:
        with open(page) as f:
            content = f.read()
    except OSError as error:
        raise ValueError(f'--page {page}: {error.strerror}') from None
    if content.count(begin) != 1 or content.count(end) != 1 or \
            content.index(begin) > content.index(end):
        raise ValueError(f'{page} has no {begin} ... {end} markers for {name} (name the '
                         'markers after --out, or --page "" for none)')
    return content


def stamp():
    """When and where a study ran, for its page: the date and the machine (cores, memory,
    whether it has a GPU)."""
    memory = os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2 ** 30
    gpu = 'a GPU' if shutil.which('nvidia-smi') else 'no GPU'
    return (f'{datetime.date.today().isoformat()}, {os.cpu_count()} cores, '
            f'{memory:.0f} GiB, {gpu}')


def marker_name(out):
    """The page markers a study writes between: named after its --out folder (the manifest's
    entry name)."""
    return os.path.basename(os.path.normpath(out))


def write_into_page(page, name, text):
    """Put `text` into the docs page `page` between its markers `<!-- name:begin -->` and
    `<!-- name:end -->` (ValueError if it has none), so the page shows what the study made."""
    begin, end = f'<!-- {name}:begin -->', f'<!-- {name}:end -->'
    content = check_page(page, name)
    head, rest = content.split(begin)
    _, tail = rest.split(end)
    with open(page, 'w') as f:
        f.write(f'{head}{begin}\n{text.rstrip()}\n{end}{tail}')


def copy_figure(page, source, name):
    """Copy a study's plot `source` to `name` (a path relative to the page's folder, e.g.
    figures/prediction.png), where the page links it; the folder is made if needed."""
    path = os.path.join(os.path.dirname(page), name)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    shutil.copyfile(source, path)
    return path
