"""A campaign's rows on disk, kept as each run ends: nothing is lost when the driver is killed.

    <out>/spec.yaml          the campaign (canonical form), written before any run
    <out>/rows/<run>.<law>.parquet   one small file per finished (run, law), written atomically
    <out>/runs.parquet       every row, consolidated from rows/ at the end and on resume

A part file is written to a temporary name and moved into place (`os.replace`, atomic on one
file system), so a part file that exists is whole; a temporary left by a killed driver is
ignored and removed on resume.
"""

import os

import yaml

SPEC_FILE = 'spec.yaml'
ROWS_DIR = 'rows'
RUNS_FILE = 'runs.parquet'
#: Columns that time the run: they differ from one flight of the same case to the next.
TIMING_COLUMNS = ('compute_median_ms', 'run_seconds')
_TEMPORARY = '.partial-'


def part_name(run, label):
    return f'{run:06d}.{label}.parquet'


def _atomic(path, write):
    directory, name = os.path.split(path)
    temporary = os.path.join(directory, f'{_TEMPORARY}{os.getpid()}-{name}')
    write(temporary)
    os.replace(temporary, path)


def write_row(out, row):
    """One finished run's row as its own part file under <out>/rows/."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    directory = os.path.join(out, ROWS_DIR)
    os.makedirs(directory, exist_ok=True)
    table = pa.Table.from_pylist([row])
    _atomic(os.path.join(directory, part_name(row['run'], row['law'])),
            lambda path: pq.write_table(table, path))


def finished_pairs(out):
    """{(run, law label)} whose rows are on disk (safe to call while a campaign runs)."""
    directory = os.path.join(out, ROWS_DIR)
    pairs = set()
    for name in os.listdir(directory) if os.path.isdir(directory) else ():
        if name.endswith('.parquet') and not name.startswith(_TEMPORARY):
            run, label, _ = name.split('.')
            pairs.add((int(run), label))
    return pairs


def remove_temporaries(out):
    """The half-written files a killed driver left (only the driver of `out` calls this)."""
    directory = os.path.join(out, ROWS_DIR)
    for name in os.listdir(directory) if os.path.isdir(directory) else ():
        if name.startswith(_TEMPORARY):
            os.remove(os.path.join(directory, name))


def consolidate(out):
    """<out>/runs.parquet from every part file, ordered by run and law; returns the rows
    (a pandas DataFrame)."""
    import pandas as pd
    directory = os.path.join(out, ROWS_DIR)
    names = sorted(n for n in os.listdir(directory)
                   if n.endswith('.parquet') and not n.startswith(_TEMPORARY)) \
        if os.path.isdir(directory) else []
    frames = [pd.read_parquet(os.path.join(directory, n)) for n in names]
    rows = (pd.concat(frames, ignore_index=True) if frames else pd.DataFrame())
    if len(rows):
        rows = rows.sort_values(['run', 'law'], kind='stable').reset_index(drop=True)
    _atomic(os.path.join(out, RUNS_FILE), lambda path: rows.to_parquet(path, index=False))
    return rows


def read_rows(out):
    """The rows of a campaign directory (runs.parquet, consolidated first if part files are
    newer: a campaign still running or killed)."""
    return consolidate(out)


def write_spec(out, spec):
    os.makedirs(out, exist_ok=True)

    def write(path):
        with open(path, 'w') as stream:
            yaml.safe_dump(spec, stream, sort_keys=False)
    _atomic(os.path.join(out, SPEC_FILE), write)


def read_spec(out):
    """The canonical spec stored in <out>/spec.yaml, or None if there is none."""
    path = os.path.join(out, SPEC_FILE)
    if not os.path.isfile(path):
        return None
    with open(path) as stream:
        return yaml.safe_load(stream)
