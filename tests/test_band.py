"""The medium policy's band search, on score curves (the rule) and on a real PPO learner (the wiring)."""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from adaptdiffuser.families.locomotion.band import Band, BandNotReachedError, SearchState, search_band
from adaptdiffuser.families.locomotion.behaviour import (
    _Learner,
    _load_search,
    _Recorder,
    _SimEnv,
    _versions,
    collect_locomotion_dataset,
    load_behaviour_policy,
    make_learner,
    record_medium_rollouts,
    train_behaviour,
)
from adaptdiffuser.families.locomotion.family import episode_returns
from adaptdiffuser.families.locomotion.params import BehaviourSettings
from adaptdiffuser.families.locomotion.reference import normalized_score
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator

BAND = Band(33.0, 3.0)


class CurveTrainee:
    """A learner whose score is ``curve(steps)``; going back returns to the snapshot's steps."""

    def __init__(self, curve: Callable[[int], float]) -> None:
        self.curve, self.at, self.band_measured, self.stderr = curve, 0, 0, 0.0
        self.confirmed: list[int] = []  # the steps of each dataset recorded

    def train(self, steps: int) -> int:
        self.at += steps
        return steps

    def steps(self) -> int:
        return self.at

    def quick_score(self) -> float:
        return self.curve(self.at)

    def band_score(self) -> tuple[float, float]:
        self.band_measured += 1
        return self.curve(self.at), self.stderr

    def confirm_score(self) -> tuple[float, float]:
        self.confirmed.append(self.at)
        return self.curve(self.at), self.stderr

    def snapshot(self) -> int:
        return self.at

    def restore(self, snapshot: int, attempt: int) -> None:
        self.at = snapshot


def jumping_curve(steps: int) -> float:
    """Rises slowly to 28 at 81 920 steps, then 37.4 points in 20 480 steps (to 65.4): evaluations every 20 480
    steps see 28 then 65.4, never the band 30..36 crossed between them."""
    if steps <= 81_920:
        return 28.0 * steps / 81_920
    return 28.0 + 37.4 * (steps - 81_920) / 20_480


def test_a_curve_that_jumps_over_the_band_is_searched_back_into_it() -> None:
    trainee, records = CurveTrainee(jumping_curve), []
    choice = search_band(trainee, BAND, 20_480, 2_048, 300_000, records.append)
    # "first evaluation at or above the target" would take 65.4 at 102 400 steps
    assert choice.score in BAND and 81_920 < choice.steps < 102_400
    assert choice.score == pytest.approx(jumping_curve(choice.steps))
    assert choice.rewinds == 2 and [r["action"] for r in records][-4:] == ["continue", "rewind", "rewind", "choose"]
    assert records[4] == {"steps": 102_400, "spent": 102_400, "quick_score": 65.4, "action": "rewind",
                          "next_interval": 5_120}  # fmt: skip
    assert choice.spent == sum(r["steps"] - p for r, p in zip(records, [0, *[20_480 * i for i in range(1, 5)],
                                                                          81_920, 81_920], strict=True))  # fmt: skip
    assert all("band_score" in r for r in records if r["action"] == "choose")


class Interrupted(Exception):
    """A search stopped from outside."""


def test_a_search_interrupted_anywhere_continues_from_its_saved_state_as_if_never_stopped() -> None:
    """The jumping curve's search (continues, then two rewinds) is stopped before each of its chunks in turn; the
    state saved there, with the trainee as it was, gives the same evaluations and choice as the straight search."""
    straight_records: list[dict] = []
    straight = search_band(CurveTrainee(jumping_curve), BAND, 20_480, 2_048, 300_000, straight_records.append)
    for stop_at in range(1, len(straight_records)):
        trainee, records, seen = CurveTrainee(jumping_curve), [], []

        def save_then_stop(
            state: SearchState, trainee: CurveTrainee = trainee, seen: list = seen, stop_at: int = stop_at
        ) -> None:
            seen.append((copy.deepcopy(state), trainee.at))
            if len(seen) > stop_at:
                raise Interrupted

        with pytest.raises(Interrupted):
            search_band(trainee, BAND, 20_480, 2_048, 300_000, records.append, on_state=save_then_stop)
        state, at = seen[-1]
        again = CurveTrainee(jumping_curve)
        again.at = at
        choice = search_band(again, BAND, 20_480, 2_048, 300_000, records.append, state=state)
        assert choice == straight and records == straight_records, f"stopped before chunk {stop_at + 1}"


def test_a_curve_that_never_reaches_the_band_is_refused_naming_the_settings() -> None:
    trainee = CurveTrainee(lambda steps: min(20.0, steps / 1_000))
    with pytest.raises(BandNotReachedError, match=r"30\.\.36 within 100000 .*highest 20\.0.*max_train_steps"):
        search_band(trainee, BAND, 10_000, 2_048, 100_000, setting="task.hopper-medium.behaviour")
    assert trainee.at == 100_000


def test_a_score_is_confirmed_before_it_is_chosen() -> None:
    """A cheap score inside the band whose dataset scores below it does not end the search."""
    trainee = CurveTrainee(lambda steps: 31.0 + steps / 10_000)
    trainee.band_score = lambda: (trainee.curve(trainee.at) - 3.0, 0.0)  # type: ignore[method-assign]
    choice = search_band(trainee, BAND, 10_000, 2_048, 100_000)
    assert choice.steps == 20_000  # at 10 000: 32 quick, 29 on the band episodes
    assert choice.score == pytest.approx(33.0)  # the dataset's score (here the curve itself) is the one kept


def test_a_lucky_band_score_is_not_chosen_when_its_dataset_scores_below_the_band() -> None:
    """The band score of the policy the search stops at is biased up (it is the luckiest of many measured on the
    same episodes); the dataset decides: 3 points of luck at 28.5 pass the band score, not the dataset."""
    trainee = CurveTrainee(lambda steps: 27.0 + steps / 10_000)
    trainee.band_score = lambda: (trainee.curve(trainee.at) + 3.0, 0.5)  # type: ignore[method-assign]
    trainee.stderr = 0.5
    records: list[dict] = []
    choice = search_band(trainee, BAND, 5_000, 2_048, 100_000, records.append)
    assert trainee.confirmed[0] == 5_000  # 27.5 + 3 = 30.5 holds; fresh 27.5 does not
    assert choice.steps == 35_000 and choice.score == pytest.approx(30.5) and choice.stderr == 0.5  # the dataset's
    assert records[0]["action"] == "continue" and records[0]["confirm_score"] == pytest.approx(27.5)
    assert records[-1]["action"] == "choose" and records[-1]["band_score"] == pytest.approx(33.5)


def test_a_score_inside_the_band_by_less_than_its_stderr_is_not_chosen() -> None:
    """30.5 +- 1 could well be a 29.5 policy: training goes on until the score is inside by more than its error."""
    trainee = CurveTrainee(lambda steps: 29.0 + steps / 2_000)
    trainee.stderr = 1.0
    records: list[dict] = []
    choice = search_band(trainee, BAND, 1_000, 1_000, 100_000, records.append)
    assert [r["band_score"] for r in records if r["action"] == "continue" and "band_score" in r][-1] == 30.5
    assert choice.steps == 4_000 and choice.score == 31.0 and choice.stderr == 1.0


def test_recorder_truncation_ends_the_cut_episode_with_a_timeout() -> None:
    recorder = _Recorder()
    for _ in range(5):
        recorder.add(0, np.zeros(2), np.zeros(3), np.zeros(1), 1.0, False, False)
    recorder.add(1, np.zeros(2), np.zeros(3), np.zeros(1), 1.0, False, False)
    recorder.truncate(3)
    cols = recorder.columns()
    assert len(recorder) == 3 and cols["timeout"].tolist() == [False, False, True]


TINY = {"max_train_steps": 600, "eval_every": 150, "min_eval_every": 150, "eval_episodes": 1, "band_episodes": 2,
        "dataset_steps": 200, "episode_steps": 60, "net_arch": [32, 32], "torch_threads": 1, "ppo_n_steps": 150,
        "batch_size": 50}  # fmt: skip


def test_a_real_learner_goes_back_and_is_refused_when_every_score_is_above_the_band(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PPO on Hopper with a band below anything it scores: every evaluation sends it back to its start (reloaded
    learner, reseeded, replay cut), until the budget is spent; the curve shows each try. Training, reloaded or not,
    leaves no SB3 log folder in the temporary directory (its default logger makes one per call)."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    settings = BehaviourSettings(seed=0, medium_score=-500.0, medium_band=1.0, **TINY)
    with pytest.raises(BandNotReachedError, match="within 600 training steps .*went back 4 times"):
        train_behaviour("Hopper-v5", tmp_path, settings)
    assert list(scratch.glob("SB3-*")) == []
    curve = json.loads((tmp_path / "behaviour.json").read_text())["curve"]
    assert [p["action"] for p in curve] == ["rewind"] * 4
    assert [p["steps"] for p in curve] == [150] * 4 and [p["spent"] for p in curve] == [150, 300, 450, 600]


def test_a_real_learner_is_chosen_inside_the_band_with_its_replay(tmp_path: Path) -> None:
    settings = BehaviourSettings(seed=0, medium_score=0.0, medium_band=100.0, **TINY)
    result = train_behaviour("Hopper-v5", tmp_path, settings)
    summary = json.loads((tmp_path / "behaviour.json").read_text())
    medium = summary["medium"]
    assert medium["band"] == [-100.0, 100.0] and medium["steps"] == 150 and medium["rewinds"] == 0
    last = summary["curve"][-1]  # the recorded score is the dataset's, not the band episodes'
    assert medium["score_of"] == "dataset" and medium["normalized_score"] == last["confirm_score"]
    assert medium["score_stderr"] == last["confirm_stderr"] >= 0.0 and last["confirm_score"] != last["band_score"]
    assert result.medium_rollouts is not None and len(result.medium_rollouts["episode"]) == 200
    assert medium["score_episodes"] == len(np.unique(result.medium_rollouts["episode"])) > 1
    assert len(result.replay["episode"]) == 150 and (tmp_path / "medium.zip").exists()


def test_the_collected_dataset_scores_what_the_band_search_recorded(tmp_path: Path) -> None:
    """The band's promise is about the dataset: the stored dataset, scored as the reference stage scores it, is
    exactly the chosen policy's recorded score, and it is the chosen policy's rollouts recorded again."""
    settings = BehaviourSettings(seed=0, medium_score=0.0, medium_band=100.0, **TINY)
    traj = collect_locomotion_dataset("hopper-medium", tmp_path / "collect", settings)
    medium = json.loads((tmp_path / "collect" / "behaviour.json").read_text())["medium"]
    scores = normalized_score(episode_returns(traj), "Hopper-v5")
    assert len(traj.episode_id) == 200 and len(scores) == medium["score_episodes"]
    assert float(scores.mean()) == medium["normalized_score"]
    sim = LocomotionSimulator("Hopper-v5", episode_steps=60)
    again = record_medium_rollouts(load_behaviour_policy(tmp_path / "collect"), sim, settings)
    np.testing.assert_array_equal(again["action"].astype(np.float32), traj.action)


@pytest.mark.parametrize("algorithm", ["ppo", "sac"])
def test_a_learners_exact_state_goes_on_as_the_learner_itself(algorithm: str) -> None:
    """Mid-episode, with its buffers and the global random streams: the restored learner takes the same training
    path (weights and recorded replay) as the one it was saved from; SAC's replay buffer, allocated for a million
    steps, is saved as its filled rows only."""
    settings = BehaviourSettings(algorithm=algorithm, seed=3, learning_starts=50, **TINY)
    eval_sim = LocomotionSimulator("Hopper-v5", episode_steps=70)
    recorder = _Recorder()
    env = _SimEnv(LocomotionSimulator("Hopper-v5", episode_steps=70), recorder)
    learner = _Learner(make_learner(env, settings), env, recorder, eval_sim, settings, lambda: None)
    learner.train(170)  # 170 (SAC) or 300 (PPO, whole rollouts of 150) steps: not at an episode's end
    saved = learner.exact_state()
    learner.train(170)
    again = _Learner.from_exact_state(saved, eval_sim, settings, lambda: None)
    again.train(170)
    for a, b in zip(learner.learner.policy.parameters(), again.learner.policy.parameters(), strict=True):
        assert np.array_equal(a.detach().numpy(), b.detach().numpy())
    for key, column in recorder.columns().items():
        np.testing.assert_array_equal(column, again.recorder.columns()[key], err_msg=key)
    assert len(recorder) == learner.steps() == again.steps() and len(saved) < 5_000_000


def test_a_killed_behaviour_search_resumes_where_it_stopped(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A real search in a process of its own, SIGKILLed once it has saved its state: run again, it resumes from that
    state and ends with the evaluations of an uninterrupted search (here refused: the band is out of reach)."""
    settings = BehaviourSettings(seed=0, medium_score=80.0, medium_band=1.0, **{**TINY, "max_train_steps": 1500})
    resume = tmp_path / "resume" / "search.pkl"
    script = textwrap.dedent(f"""
        from pathlib import Path
        from adaptdiffuser.families.locomotion.behaviour import train_behaviour
        from adaptdiffuser.families.locomotion.params import BehaviourSettings
        settings = BehaviourSettings.model_validate_json({settings.model_dump_json()!r})
        train_behaviour("Hopper-v5", Path({str(tmp_path / "killed")!r}), settings, resume_path=Path({str(resume)!r}),
                        checkpoint_every_s=0.0)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)  # fmt: skip
    while proc.poll() is None and not resume.exists():
        time.sleep(0.01)
    assert proc.poll() is None, f"the search ended before it was killed: {proc.stderr.read().decode()}"
    os.killpg(proc.pid, signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL
    killed_after = len(json.loads((tmp_path / "killed" / "behaviour.json").read_text())["curve"])
    key = {"env_id": "Hopper-v5", "settings": settings.model_dump(), "tag": None, "versions": _versions()}
    assert _load_search(resume, key) is not None
    assert _load_search(resume, {**key, "tag": "other code"}) is None  # taken up only by the same code
    assert _load_search(resume, {**key, "settings": {**key["settings"], "seed": 1}}) is None
    assert _load_search(resume, {**key, "versions": {**key["versions"], "torch": "0.0"}}) is None

    with pytest.raises(BandNotReachedError):
        train_behaviour("Hopper-v5", tmp_path / "straight", settings)
    capsys.readouterr()
    with pytest.raises(BandNotReachedError):
        train_behaviour("Hopper-v5", tmp_path / "killed", settings, resume_path=resume, checkpoint_every_s=0.0)
    assert "resuming the behaviour search after" in capsys.readouterr().out
    assert not resume.exists()  # refused: the state is of no more use

    def curve(name: str) -> list[dict]:
        points = json.loads((tmp_path / name / "behaviour.json").read_text())["curve"]
        return [{key: value for key, value in point.items() if key != "wall_s"} for point in points]

    assert len(curve("straight")) == 10 and 1 <= killed_after < 10
    assert curve("killed") == curve("straight")


def test_an_unreadable_search_state_is_ignored_and_the_search_starts_over(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A state cut short (a disk that filled up) or written by other code: the search starts over, saying why."""
    settings = BehaviourSettings(seed=0, medium_score=0.0, medium_band=100.0, **TINY)
    resume = tmp_path / "search.pkl"
    resume.write_bytes(b"\x80\x05 not a whole pickle")
    result = train_behaviour("Hopper-v5", tmp_path / "out", settings, resume_path=resume, checkpoint_every_s=0.0)
    assert "ignoring behaviour search state" in capsys.readouterr().out
    assert result.medium["steps"] == 150 and not resume.exists()
