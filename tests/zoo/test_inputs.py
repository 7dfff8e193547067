"""The checks of input that the commands share: counts, output paths, ``--env-kwargs`` and the model source."""

import pytest

from sb3_spikeplastic.zoo.inputs import check_int, check_output_path, model_source, parse_env_kwargs


def test_check_int_names_the_option_and_the_minimum():
    check_int("--episodes", None, 1)  # not given
    check_int("--episodes", 1, 1)
    with pytest.raises(ValueError, match=r"^--episodes=0 must be >= 1$"):
        check_int("--episodes", 0, 1)


def test_output_paths_must_be_writable_where_they_are(tmp_path):
    (tmp_path / "afile").write_text("")
    assert check_output_path(tmp_path / "new" / "deeper", "-o", directory=True) == tmp_path / "new" / "deeper"
    assert check_output_path(tmp_path / "x.png", "-o", directory=False) == tmp_path / "x.png"
    cases = [
        (tmp_path / "afile", True, "is a file, not a folder"),
        (tmp_path, False, "is a folder, not a file"),
        (tmp_path / "afile" / "x.png", False, f"lies under the file {str(tmp_path / 'afile')!r}"),
    ]
    for path, directory, message in cases:
        with pytest.raises(ValueError, match=message):
            check_output_path(path, "-o", directory=directory)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing created


def test_env_kwargs_are_yaml_values_of_plain_keys():
    assert parse_env_kwargs(None) is None
    assert parse_env_kwargs(["max_episode_steps=200", "noise=high", "cues=[0, 1]"]) == {
        "max_episode_steps": 200,
        "noise": "high",
        "cues": [0, 1],
    }
    with pytest.raises(ValueError, match="malformed --env-kwargs entry 'a.b=1'; expected key=value"):
        parse_env_kwargs(["a.b=1"])
    with pytest.raises(ValueError, match="--env-kwargs entry"):
        parse_env_kwargs(["noequals"])


def test_model_source_needs_exactly_one_model_and_an_environment(tmp_path):
    with pytest.raises(ValueError, match="give either --run FOLDER or --model PATH"):
        model_source()
    with pytest.raises(ValueError, match="give either --run FOLDER or --model PATH"):
        model_source(run="a", model="b")
    (tmp_path / "model.zip").write_bytes(b"")
    with pytest.raises(ValueError, match="--env is needed"):
        model_source(model=str(tmp_path / "model.zip"))
    with pytest.raises(ValueError, match="no VecNormalize statistics file 'missing.pkl'"):
        model_source(model=str(tmp_path / "model.zip"), vecnormalize="missing.pkl")
    info, env_id = model_source(
        model=str(tmp_path / "model.zip"), env="TMazeCue-v0", env_kwargs=["max_episode_steps=7"]
    )
    assert env_id == "TMazeCue-v0" and info.env_kwargs == {"max_episode_steps": 7} and info.vecnormalize is None
    with pytest.raises(FileNotFoundError, match="no run folder or model file"):
        model_source(run=str(tmp_path / "nowhere"))
