"""A resumed `rotate collect` adopts only the sessions it wrote: every kept file carries the collection's settings
digest and its own episode index, and holds the streams these settings record; any other file at an episode's path
is refused in one line and left as it is (issue "Nothing written before the request is checked")."""

from __future__ import annotations

import shutil

import h5py
import pytest

from rotation.cli import main
from rotation.jobs import collect, collect_resume


def cfg_for(out, **kw) -> collect.Config:
    return collect.Config(**{**dict(out=out, episodes=2, num_envs=1, episode_steps=3, seed=5, progress=False), **kw})


@pytest.fixture
def two_collections(tmp_path):
    """Two finished collections of two episodes each, differing only in their seed."""
    a, b = tmp_path / "a", tmp_path / "b"
    collect.run(cfg_for(a))
    collect.run(cfg_for(b, seed=6))
    return a, b


def _refused_and_untouched(out, path, capsys, words: str) -> None:
    before = path.read_bytes()
    assert main(["collect", "--out", str(out), "--episodes", "3", "--num-envs", "1", "--episode-steps", "3",
                 "--seed", "5", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("rotate collect: refused: ") and str(path) in err and words in err, err
    assert path.read_bytes() == before
    assert not collect.episode_path(out, 2).exists()  # nothing recorded either


def test_its_own_sessions_are_kept(two_collections):
    a, _ = two_collections
    stamps = [collect.episode_path(a, e).stat().st_mtime_ns for e in (0, 1)]
    collect.run(cfg_for(a, episodes=3))
    assert [collect.episode_path(a, e).stat().st_mtime_ns for e in (0, 1)] == stamps
    assert collect_resume.is_complete(collect.episode_path(a, 2))


def test_a_session_of_another_collection_is_refused(two_collections, capsys):
    a, b = two_collections
    shutil.copyfile(collect.episode_path(b, 1), collect.episode_path(a, 1))  # same streams, other settings
    _refused_and_untouched(a, collect.episode_path(a, 1), capsys, "was not written by this collection")


def test_its_own_session_at_another_episode_is_refused(two_collections, capsys):
    a, _ = two_collections
    shutil.copyfile(collect.episode_path(a, 0), collect.episode_path(a, 1))
    _refused_and_untouched(a, collect.episode_path(a, 1), capsys, "records episode 0")


def test_a_file_that_is_not_its_session_is_refused(two_collections, capsys):
    a, _ = two_collections
    path = collect.episode_path(a, 1)
    path.unlink()
    with h5py.File(path, "w") as f:  # a file with no session in it (or a deploy recording: no settings digest)
        f["x"] = [1]
    _refused_and_untouched(a, path, capsys, "is not a session this collection wrote")


def test_a_session_without_the_streams_its_settings_record_is_refused(two_collections, capsys):
    a, _ = two_collections
    path = collect.episode_path(a, 1)
    with h5py.File(path, "r+") as f:
        del f["streams/digit360/thumb/contact"]
    _refused_and_untouched(a, path, capsys, "digit360/thumb/contact")
