"""Where a study lives, as --storage names it: a journal file (processes on one machine share
it) or a database URL for Optuna's RDB storage (`postgresql://user:password@host:port/db`: the
way several machines share one study; `sqlite:///file.db` for one machine)."""

import json
import os


def is_url(storage):
    return '://' in storage


def shown(storage):
    """`storage` as messages print it: a URL without its password."""
    if not is_url(storage):
        return storage
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError
    try:
        return make_url(storage).render_as_string(hide_password=True)
    except ArgumentError:
        return storage.split('://', 1)[0] + '://...'


def check_journal(storage):
    """A journal file given as --storage must be absent, empty or a journal: Optuna would
    append its records to any other file before failing."""
    if is_url(storage) or not os.path.isfile(storage) or os.path.getsize(storage) == 0:
        return
    with open(storage, 'rb') as stream:
        first = stream.readline(1 << 16)
    try:
        record = json.loads(first)
    except ValueError:
        record = None
    if not (isinstance(record, dict) and 'op_code' in record):
        raise ValueError(f'--storage {storage} is not an Optuna journal file; nothing was '
                         'written to it')


def open_storage(storage):
    """The Optuna storage `storage` names; ValueError in one line where a database cannot be
    reached or its URL is not one (a journal file's directory is made)."""
    import optuna
    if not is_url(storage):
        check_journal(storage)
        os.makedirs(os.path.dirname(os.path.abspath(storage)), exist_ok=True)
        return optuna.storages.JournalStorage(
            optuna.storages.journal.JournalFileBackend(storage))
    from sqlalchemy.exc import SQLAlchemyError
    try:
        return optuna.storages.RDBStorage(storage)
    except (SQLAlchemyError, ImportError, ValueError) as error:
        # The driver's message may run over lines and repeat the URL, password included.
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ValueError(f'--storage {shown(storage)}: cannot open the database: '
                         f'{first.replace(storage, shown(storage))}') from None
