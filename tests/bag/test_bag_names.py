"""Bag names: distinct for deployments started in the same second, never an existing directory.
(Two recorders started at once: tests/bag/test_runs_over_dds.py.)"""

import datetime
import re

import pytest

from tsr_koopman_ctrl.bag import writer
from tsr_koopman_ctrl.deployment import Deployment


def test_two_deployments_started_in_the_same_second_get_distinct_bags(tmp_path):
    first, second = (Deployment('linear_lqr', bags=str(tmp_path), logs=str(tmp_path / 'logs'))
                     for _ in range(2))
    assert first.bag != second.bag
    for deployment in (first, second):
        assert re.fullmatch(r'deploy_linear_lqr_\d{8}_\d{6}_\d{6}_[0-9a-f]{6}', deployment.name)
    with pytest.raises(ValueError, match=f'bag {tmp_path}/taken exists: give another name'):
        (tmp_path / 'taken').mkdir()
        Deployment('linear_lqr', bags=str(tmp_path), logs=str(tmp_path / 'logs'), name='taken')


def test_a_name_whose_directory_exists_is_drawn_again(tmp_path, monkeypatch):
    """Same microsecond, same random draw: the second name is drawn again, not reused."""
    class FrozenClock:
        timezone = datetime.timezone

        class datetime:
            @staticmethod
            def now(tz):
                return datetime.datetime(2030, 1, 2, 3, 4, 5, 678901, tzinfo=tz)

    draws = iter(['aaaaaa', 'aaaaaa', 'bbbbbb'])
    monkeypatch.setattr(writer, 'datetime', FrozenClock)
    monkeypatch.setattr(writer.secrets, 'token_hex', lambda size: next(draws))
    first = writer.new_bag_name(str(tmp_path), 'tsr')
    assert first == 'tsr_20300102_030405_678901_aaaaaa'
    (tmp_path / first).mkdir()
    assert writer.new_bag_name(str(tmp_path), 'tsr') == 'tsr_20300102_030405_678901_bbbbbb'
