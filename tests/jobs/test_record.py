"""`rotate record`: a labelled session or a clear refusal before the hand starts; the written session is judged as
`rotate finetune-adapter` judges its sessions."""

from __future__ import annotations

import json

import pytest
from deploy_checks import load_fault

from envs.errors import RequestRefused
from rotation.cli import main
from rotation.data.session_reader import SessionReader
from rotation.jobs import record
from rotation.policy.bundle import shipped_bundles

REAL = dict(hand="allegro", policy="student", record="s.h5", digit360="D360-A,D360-B,D360-C,D360-D")


def _card(tmp_path, **values) -> str:
    path = tmp_path / "card.json"
    path.write_text(json.dumps(values))
    return str(path)


def test_a_card_and_the_options_make_the_labels(tmp_path):
    card = _card(tmp_path, object="mug_tape", mass=0.21, friction=0.8, friction_method="tilt, 5 trials",
                 com=[0, 0, 0.01], scale=0.9, notes="tape on the body")
    name, props, method = record.resolve_labels(record.Config(**REAL, object_card=card, properties="friction=0.45"),
                                                interactive=False)
    assert name == "mug_tape" and method == "tilt, 5 trials"
    assert props == {"mass": 0.21, "friction": 0.45, "com": [0, 0, 0.01], "scale": 0.9}  # the option overrides


def test_missing_properties_are_asked_in_a_terminal_and_a_bad_answer_is_asked_again(tmp_path, capsys):
    answers = iter(["0.3 kg", "0.3", "0.6", "0,0.005", "0,0,0.005", "12", "0.85", "pull: force gauge"])
    asked = []

    def prompt(question: str) -> str:
        asked.append(question)
        return next(answers)

    was_asked: list[str] = []
    name, props, method = record.resolve_labels(record.Config(**REAL), interactive=True, prompt=prompt,
                                                asked=was_asked)
    assert props == {"mass": 0.3, "friction": 0.6, "com": [0, 0, 0.005], "scale": 0.85}
    assert was_asked == ["mass", "friction", "com", "scale", "friction_method"]
    assert method == "pull: force gauge" and len(asked) == 8
    err = capsys.readouterr().err
    # '0.3 kg', two numbers for the center of mass, then a scale of 12: each said and asked again
    assert "is not a number" in err and "must be 3 numbers" in err and "outside" in err and "give KEY" not in err


def test_answers_are_saved_as_a_card_that_reads_back_and_an_existing_file_is_kept(tmp_path, capsys):
    path = tmp_path / "s.card.json"
    props = {"mass": 0.3, "friction": 0.6, "com": [0, 0, 0.005], "scale": 0.85}
    record.save_card(path, "mug", props, "pull")
    card = record.read_card(str(path))
    assert card == {"object": "mug", **props, "friction_method": "pull"}
    record.save_card(path, "other", props, "tilt")
    assert record.read_card(str(path))["object"] == "mug" and "were not saved" in capsys.readouterr().err


@pytest.mark.parametrize("kw, words", [
    (dict(properties="mass=0.2,friction=0.5"), "lack the object's com, scale"),
    (dict(properties="mass=0.2,friction=0.5,com=0,0,0,scale=0.8"), "how the friction coefficient was measured"),
])
def test_a_real_session_without_its_labels_is_refused_outside_a_terminal(kw, words):
    with pytest.raises(RequestRefused, match=words):
        record.resolve_labels(record.Config(**REAL, **kw), interactive=False)


@pytest.mark.parametrize("content, words", [
    ("{", "not JSON"), ("[1, 2]", "one JSON object"), ('{"weight": 0.2}', "unknown key(s) weight"),
    ('{"mass": 20}', "outside"), ('{"mass": 0.2, "friction_method": 3}', "must be text"),
])
def test_bad_object_cards_are_refused_with_the_file_and_the_key(tmp_path, content, words):
    path = tmp_path / "card.json"
    path.write_text(content)
    with pytest.raises(ValueError, match="object card") as err:
        record.read_card(str(path))
    assert words in str(err.value)
    with pytest.raises(ValueError, match="cannot read it"):
        record.read_card(str(tmp_path / "none.json"))


def test_cli_refusals_are_one_line_before_anything_starts(tmp_path, capsys):
    base = ["record", "--hand", "allegro", "--policy", "student", "--record", str(tmp_path / "s.h5"), "--no-ask"]
    labels = ["--properties", "mass=0.2,friction=0.5,com=0,0,0,scale=0.8", "--friction-method", "tilt"]
    assert main([*base, *labels]) == 1  # no fingertips
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "give the Digit 360 fingertips" in err
    assert main([*base, *labels, "--digit360", "a,b,c,d", "--duration", "2"]) == 2
    assert "at least 5 s" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # argparse: a required option is missing
        main(["record", "--hand", "sim-allegro", "--policy", "student", "--duration", "5"])
    assert exit_.value.code == 2 and "required: --record" in capsys.readouterr().err
    assert not (tmp_path / "s.h5").exists()


@pytest.mark.skipif("student" not in shipped_bundles(), reason="needs the shipped student")
def test_an_emulated_labelled_session_is_judged_usable_and_a_faulted_one_kept(tmp_path, capsys):
    common = ["record", "--hand", "sim-allegro", "--policy", "student", "--digit360", "sim", "--duration", "5",
              "--status-every-s", "10", "--sim-object", "mass=0.2,friction=0.6"]
    code = main([*common, "--record", str(tmp_path / "a.h5"), "--sim-faults", "unplug=ring@3"])
    out = capsys.readouterr()
    summary = json.loads(out.out.strip().splitlines()[-1])
    if load_fault(summary):
        pytest.skip(f"the machine was too loaded to run the loop: {summary['fault']}")
    assert code == 0, summary["fault"]
    verdict = summary["finetune_ready"]
    assert verdict["usable"] and verdict["complete"] and verdict["fingers"] == ["index", "middle", "ring", "thumb"]
    assert verdict["properties"]["mass"] == pytest.approx(0.2) and verdict["windows"] == ["imu", "pressure"]
    assert "usable by `rotate finetune-adapter --sessions`" in out.err
    with SessionReader(tmp_path / "a.h5") as r:
        assert r.meta.properties["friction_method"] == "emulator"

    code = main([*common, "--record", str(tmp_path / "b.h5"), "--sim-faults", "bus-error=2"])
    out = capsys.readouterr()
    summary = json.loads(out.out.strip().splitlines()[-1])
    assert code == 1 and "error frame" in summary["fault"]
    assert summary["finetune_ready"]["usable"] and not summary["finetune_ready"]["complete"]
    assert "the run ended early" in out.err
