"""Hyperparameter files: the packaged ppo.yml and paper.yml, overrides (and the keys a whole-mapping override
drops), validation, the safe string parser, model construction."""

import inspect

import gymnasium as gym
import pytest
import torch
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_spikeplastic
from sb3_spikeplastic import PPO, SpikePlasticPolicy, cli
from sb3_spikeplastic.zoo import validation as config
from sb3_spikeplastic.zoo.config import (
    load_hyperparams,
    model_arguments,
    normalize_arguments,
    replaced_mappings,
    resolve_hyperparams,
)
from sb3_spikeplastic.zoo.validation import algorithm_class
from sb3_spikeplastic.zoo.zoo_yaml import (
    default_hyperparams_path,
    load_hyperparams_file,
    parse_override,
    parse_python_literal,
    yaml_load,
)

ENTRIES = ("TMazeCue-v0", "TMazeCueNoisy-v0", "HalfCheetah-v5", "NoisyHalfCheetah-v5", "HalfCheetahSwitch-v5")


def test_packaged_file_is_found_and_has_the_entries():
    path = default_hyperparams_path()
    assert path.is_file() and path.name == "ppo.yml"
    data = load_hyperparams_file()
    assert {"default", *ENTRIES} <= set(data)
    for env_id in ENTRIES:
        resolved = resolve_hyperparams(env_id)
        assert resolved["policy"] == "SpikePlasticPolicy" and {"n_timesteps", "n_envs", "n_steps"} <= set(resolved)


def _default(fn, key):
    default = inspect.signature(fn).parameters[key].default
    return list(default) if isinstance(default, tuple) else default


@pytest.mark.parametrize("conf", ["ppo", "paper"])
def test_spiking_entries_state_only_what_differs_from_the_defaults(conf):
    """No value of a spiking entry (or of ``default``) repeats the default of PPO or SpikePlasticPolicy."""
    from sb3_spikeplastic.sb3.ppo import POLICY_DEPENDENT_DEFAULTS

    for env_id, entry in load_hyperparams_file(conf).items():
        if entry.get("policy", "SpikePlasticPolicy") != "SpikePlasticPolicy":
            continue
        for key, value in entry.items():
            if key in config.META_KEYS:
                continue
            default = POLICY_DEPENDENT_DEFAULTS[key][1] if key in POLICY_DEPENDENT_DEFAULTS else _default(PPO, key)
            assert value != default, (conf, env_id, key, value)
        for key, value in (entry.get("policy_kwargs") or {}).items():
            assert value != _default(SpikePlasticPolicy.__init__, key), (conf, env_id, "policy_kwargs", key, value)


@pytest.mark.parametrize("env_id", ["CartPole-v1", *ENTRIES])
def test_entries_are_consistent(env_id):
    """Chunking fits every entry; HalfCheetah normalises and starts alpha at zero mean (a positive mean makes the
    trace loop explode, tests/sb3/test_policy.py), and the packaged paper file has the paper's network and GAE
    lambda (appendix 5.2-5.5)."""
    entry = resolve_hyperparams(env_id)
    bptt, batch = entry.get("bptt_steps", _default(PPO, "bptt_steps")), entry.get("batch_size", 256)
    assert entry["n_steps"] % bptt == 0 and batch % bptt == 0
    assert batch <= entry["n_steps"] * entry["n_envs"]
    if "HalfCheetah" in env_id:
        assert entry["normalize"] is True and "alpha_init_mean" not in entry["policy_kwargs"]  # the default: 0
        paper = resolve_hyperparams(env_id, "paper")
        kwargs = paper["policy_kwargs"]
        assert (kwargs["steps"], kwargs["encoder_pop_size"], kwargs["action_pop_size"]) == (50, 50, 100)
        assert paper["normalize"] is True and paper["gae_lambda"] == 0.97 and len(kwargs["obs_indices"]) == 12
    # an id without an entry trains with `default`
    assert resolve_hyperparams("CartPole-v1")["policy_kwargs"] == {}


def _env_for(env_id, n_envs):
    make = (lambda: gym.make("CartPole-v1")) if env_id == "default" else (lambda: gym.make(env_id))
    return DummyVecEnv([make for _ in range(n_envs)])


@pytest.mark.parametrize(
    "env_id, conf", [("default", None), *[(e, None) for e in ENTRIES], ("HalfCheetah-v5", "paper")]
)
def test_every_entry_constructs_a_model(env_id, conf):
    """Construction only (no learning); the paper file's HalfCheetah network encodes 12 x 50 inputs."""
    resolved = resolve_hyperparams("CartPole-v1" if env_id == "default" else env_id, conf)
    policy, ppo_kwargs, policy_kwargs = model_arguments(resolved)
    env = _env_for(env_id, resolved["n_envs"])
    norm = normalize_arguments(resolved)
    if norm is not None:
        env = VecNormalize(env, **norm)
    model = PPO(policy, env, **ppo_kwargs, policy_kwargs=policy_kwargs, device="cpu")
    assert model.n_steps == resolved["n_steps"]
    assert model.bptt_steps == resolved.get("bptt_steps", _default(PPO, "bptt_steps"))
    if env_id.endswith("HalfCheetah-v5"):
        assert model.policy.snn.sizes == ([12 * 50, 64, 64, 6 * 100] if conf == "paper" else [17 * 10, 64, 64, 6 * 20])
    env.close()


def test_yaml_floats_without_a_dot():
    assert yaml_load("a: 1e-3\nb: 2e5\nc: 3.0\nd: 1_000\ne: .5") == {"a": 1e-3, "b": 2e5, "c": 3.0, "d": 1000, "e": 0.5}


def test_overrides_nested_and_precedence():
    resolved = resolve_hyperparams(
        "TMazeCue-v0",
        overrides=[
            "n_steps=32",
            "policy_kwargs.hidden_sizes=[16]",
            "policy_kwargs.rule=dp-bcm",
            "learning_rate=1e-4",
            "policy_kwargs.rule_kwargs.eta_init=0.1",
            "policy_kwargs.neuron.theta=12",
            "normalize=true",
            "normalize.norm_reward=false",
            "env_kwargs.noise=high",
        ],
        rule="static",
        n_timesteps=1000,
        n_envs=2,
    )
    assert resolved["n_steps"] == 32 and resolved["learning_rate"] == 1e-4
    assert resolved["policy_kwargs"]["hidden_sizes"] == [16]
    assert resolved["policy_kwargs"]["rule"] == "static"  # --rule wins over the override
    assert resolved["policy_kwargs"]["rule_kwargs"] == {"eta_init": 0.1}
    assert resolved["policy_kwargs"]["neuron"] == {"theta": 12.0}
    assert resolved["normalize"] == {"norm_reward": False}
    assert normalize_arguments(resolved) == {"norm_reward": False, "gamma": 0.99}
    assert resolved["env_kwargs"] == {"noise": "high"}
    assert (resolved["n_timesteps"], resolved["n_envs"]) == (1000, 2)


def test_default_is_merged_under_the_entry(tmp_path):
    conf = tmp_path / "my.yml"
    conf.write_text(
        "default:\n  n_epochs: 3\n  policy_kwargs: {rule: dp-bcm, steps: 20}\n"
        "CartPole-v1:\n  n_steps: 64\n  policy_kwargs: {hidden_sizes: [8]}\n"
    )
    resolved = resolve_hyperparams("CartPole-v1", conf=conf)
    assert resolved["n_epochs"] == 3 and resolved["n_steps"] == 64
    assert resolved["policy_kwargs"] == {"rule": "dp-bcm", "steps": 20, "hidden_sizes": [8]}


def test_parse_override():
    assert parse_override("n_steps=128") == (("n_steps",), 128)
    assert parse_override("policy_kwargs.hidden_sizes=[32, 32]") == (("policy_kwargs", "hidden_sizes"), [32, 32])
    assert parse_override("policy_kwargs.rule=dp-bcm") == (("policy_kwargs", "rule"), "dp-bcm")
    for bad in ("n_steps", "=3", "a..b=1", "1x=2"):
        with pytest.raises(ValueError, match="malformed hyperparameter override"):
            parse_override(bad)


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "n_stepz=3",
            r"unknown hyperparameter 'n_stepz' \(did you mean 'n_steps'\?\); accepted: .*bptt_steps.*n_steps",
        ),
        ("n_steps=abc", r"n_steps='abc' must be an integer"),
        ("gamma=high", r"gamma='high' must be a number"),
        ("n_timesteps=1.5", r"n_timesteps=1.5 must be an integer"),
        (
            "policy_kwargs.hidden_sizez=[3]",
            r"unknown policy_kwargs key 'hidden_sizez' \(did you mean 'hidden_sizes'\?\); accepted: .*hidden_sizes",
        ),
        ("policy_kwargs.hidden_sizes=16", r"policy_kwargs.hidden_sizes=16 must be a list of integers"),
        ("policy_kwargs.rule=hebb", r"unknown rule 'hebb'; accepted: static, .*dp-oja"),
        (
            "policy_kwargs.rule_kwargs.foo=1",
            r"unknown policy_kwargs.rule_kwargs key 'foo' for rule 'dp-oja'; accepted: eta_init",
        ),
        (
            "policy_kwargs.neuron.thet=1",
            r"unknown policy_kwargs.neuron key 'thet' \(did you mean 'theta'\?\); accepted: .*theta",
        ),
        ("normalize.clip_obs=5", r"normalize is False, not a mapping \(set normalize=true first\)"),
        (
            "normalize={clip_obz: 5}",
            r"unknown normalize \(VecNormalize\) key 'clip_obz' \(did you mean 'clip_obs'\?\); accepted: clip_obs",
        ),
        ("learning_rate=lin_x", r"learning_rate='lin_x' must be a number or lin_<number>"),
        ("grad_clip=layer", r"grad_clip='layer' is not accepted; accepted: global, per-parameter"),
        ("policy=TransformerPolicy", r"unknown policy 'TransformerPolicy'; accepted: .*SpikePlasticPolicy"),
        ("policy_kwargs.optimizer_class=os.system", r"'os.system' is not a class of torch.optim; accepted: .*Adam"),
    ],
)
def test_bad_values_name_the_key_and_the_accepted_ones(override, message):
    with pytest.raises(ValueError, match=message):
        resolve_hyperparams("TMazeCue-v0", overrides=[override])


def test_rule_flag_is_validated():
    with pytest.raises(ValueError, match=r"unknown rule 'hebb'; accepted: static, dp-linear, dp-oja"):
        resolve_hyperparams("TMazeCue-v0", rule="hebb")
    for rule in sb3_spikeplastic.available_rules():
        assert resolve_hyperparams("TMazeCue-v0", rule=rule)["policy_kwargs"]["rule"] == rule


def test_the_rule_flag_drops_the_files_arguments_of_another_rule():
    """``--conf paper`` sets ndp-oja's ``wm_init_gain``: ``--rule static`` drops it, ``--rule ndp-bcm`` keeps it, and
    the same argument given on the command line is still checked against the rule."""
    assert resolve_hyperparams("HalfCheetah-v5", "paper", rule="static")["policy_kwargs"]["rule_kwargs"] == {}
    assert resolve_hyperparams("HalfCheetah-v5", "paper", rule="ndp-bcm")["policy_kwargs"]["rule_kwargs"] == {
        "wm_init_gain": 5
    }
    with pytest.raises(ValueError, match="unknown policy_kwargs.rule_kwargs key 'wm_init_gain' for rule 'static'"):
        resolve_hyperparams(
            "HalfCheetah-v5", "paper", overrides=["policy_kwargs.rule_kwargs.wm_init_gain=5"], rule="static"
        )


def test_lin_schedules_and_class_names():
    resolved = resolve_hyperparams(
        "TMazeCue-v0",
        overrides=[
            "learning_rate=lin_1e-3",
            "clip_range=lin_0.2",
            "policy_kwargs.optimizer_class=th.optim.AdamW",
            "policy_kwargs.optimizer_kwargs={eps: 1.0e-5}",
        ],
    )
    policy, ppo_kwargs, policy_kwargs = model_arguments(resolved)
    assert ppo_kwargs["learning_rate"](1.0) == pytest.approx(1e-3)
    assert ppo_kwargs["learning_rate"](0.5) == pytest.approx(5e-4)
    assert ppo_kwargs["clip_range"](0.0) == 0.0
    assert policy_kwargs["optimizer_class"] is torch.optim.AdamW
    assert "n_timesteps" not in ppo_kwargs and "policy_kwargs" not in ppo_kwargs and "normalize" not in ppo_kwargs


def test_safe_policy_kwargs_string():
    assert parse_python_literal("dict(rule='dp-oja', hidden_sizes=[64])") == {"rule": "dp-oja", "hidden_sizes": [64]}
    assert parse_python_literal("dict(log_std_init=-2, net_arch=dict(pi=[64], vf=[64]), activation_fn=nn.ReLU)") == {
        "log_std_init": -2,
        "net_arch": {"pi": [64], "vf": [64]},
        "activation_fn": "nn.ReLU",
    }
    assert parse_python_literal("{'a': (1, 2.5), 'b': None, 'c': True}") == {"a": (1, 2.5), "b": None, "c": True}
    for evil in (
        "__import__('os').system('x')",
        "open('/etc/passwd')",
        "dict(**x)",
        "[x for x in ()]",
        "os.system",
        "1 + 1",
        "lambda: 0",
        "dict(a=print(1))",
    ):
        with pytest.raises(ValueError, match="unsafe or unsupported expression|not a valid Python expression"):
            parse_python_literal(evil, "policy_kwargs")


def test_rl_zoo_string_form_in_a_file_and_an_override(tmp_path):
    conf = tmp_path / "zoo.yml"
    conf.write_text(
        "TMazeCue-v0:\n  n_steps: 32\n  batch_size: 32\n  bptt_steps: 16\n"
        "  policy_kwargs: \"dict(rule='dp-bcm', hidden_sizes=[8])\"\n"
        '  normalize: "dict(norm_obs=False, norm_reward=True)"\n'
    )
    resolved = resolve_hyperparams("TMazeCue-v0", conf=conf, overrides=["policy_kwargs.hidden_sizes=[4]"])
    assert resolved["policy_kwargs"] == {"rule": "dp-bcm", "hidden_sizes": [4]}
    assert resolved["normalize"] == {"norm_obs": False, "norm_reward": True}
    with pytest.raises(ValueError, match="unsafe or unsupported expression"):
        resolve_hyperparams("TMazeCue-v0", overrides=["policy_kwargs=__import__('os').system('x')"])


def test_bad_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read hyperparameter file"):
        load_hyperparams_file(tmp_path / "missing.yml")
    (tmp_path / "bad.yml").write_text("a: [1\n")
    with pytest.raises(ValueError, match="is not valid YAML"):
        load_hyperparams_file(tmp_path / "bad.yml")
    (tmp_path / "flat.yml").write_text("n_steps: 3\n")
    with pytest.raises(ValueError, match="must map environment ids"):
        load_hyperparams_file(tmp_path / "flat.yml")
    (tmp_path / "other.yml").write_text("Pendulum-v1: {n_steps: 32}\n")
    with pytest.raises(ValueError, match="no hyperparameters for 'CartPole-v1'.*entries: Pendulum-v1"):
        resolve_hyperparams("CartPole-v1", conf=tmp_path / "other.yml")


def test_accepted_keys_follow_the_signatures():
    keys = config.accepted_keys()
    assert {"bptt_steps", "n_steps", "batch_size", "learning_rate", "n_timesteps", "policy_kwargs", "normalize"} <= set(
        keys
    )
    assert "tensorboard_log" not in keys and "seed" not in keys
    assert {"rule", "hidden_sizes", "steps", "encoder_pop_size", "action_pop_size"} <= set(config.policy_kwarg_hints())


# ----------------------------------------------------------------------------------------------------------------
# load_hyperparams: a packaged entry as Python arguments


def test_load_hyperparams_returns_the_packaged_tmaze_entry():
    raw = load_hyperparams_file("ppo")["TMazeCue-v0"]
    h = load_hyperparams("TMazeCue-v0")
    assert h.policy == "SpikePlasticPolicy" and h.algo == "ppo"
    assert (h.n_envs, h.n_timesteps, h.normalize, h.env_kwargs) == (8, raw["n_timesteps"], None, {})
    kwargs = h.model_kwargs
    assert kwargs["policy_kwargs"]["alpha_lr_scale"] == raw["policy_kwargs"]["alpha_lr_scale"]
    for key in ("n_steps", "bptt_steps", "n_epochs", "learning_rate", "use_action_masks"):
        assert kwargs[key] == raw[key], key
    assert not set(kwargs) & {"n_envs", "n_timesteps", "normalize", "env_kwargs", "policy", "algo"}


def test_load_hyperparams_rule_and_other_files():
    assert load_hyperparams("TMazeCue-v0", rule="ndp-bcm").model_kwargs["policy_kwargs"]["rule"] == "ndp-bcm"
    cheetah = load_hyperparams("HalfCheetah-v5", "paper")
    assert cheetah.normalize == {"gamma": 0.99} and cheetah.model_kwargs["learning_rate"](0.5) == pytest.approx(2.5e-4)
    lstm = load_hyperparams("HalfCheetah-v5", "ppo_lstm")
    assert (lstm.algo, lstm.policy) == ("ppo_lstm", "MlpLstmPolicy") and "algo" not in lstm.model_kwargs
    # the baselines with their own tuned settings (rl-baselines3-zoo's HalfCheetah entries) build as they say
    for conf, cls in (("mlp_zoo", "PPO"), ("ppo_lstm_zoo", "RecurrentPPO")):
        zoo = load_hyperparams("HalfCheetah-v5", conf)
        model = algorithm_class(zoo.algo)(zoo.policy, "HalfCheetah-v5", **zoo.model_kwargs)
        assert type(model).__name__ == cls and (model.n_steps, model.batch_size, model.n_epochs) == (512, 64, 20)
        assert model.learning_rate == pytest.approx(2.0633e-05) and model.policy.log_std.mean().item() == -2.0
        layers = model.policy.mlp_extractor.policy_net
        assert [m.out_features for m in layers if hasattr(m, "out_features")] == [256, 256]
    # a registered id without an entry gets `default`, as on the command line
    assert load_hyperparams("CartPole-v1").model_kwargs["policy_kwargs"] == {}
    # fresh copies: changing one result leaves the next alone
    load_hyperparams("TMazeCue-v0").model_kwargs["policy_kwargs"]["hidden_sizes"].append(3)
    assert load_hyperparams("TMazeCue-v0").model_kwargs["policy_kwargs"]["hidden_sizes"] == [64]


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ("TMazeCu-v0",),
            r"^unknown environment id 'TMazeCu-v0'; did you mean TMazeCue-v0"
            r".*accepted: an entry of the file \(TMazeCue-v0, ",
        ),
        (
            ("TMazeCue-v0", "ppo2"),
            r"^cannot read hyperparameter file 'ppo2'"
            r".*packaged files: ppo, paper, mlp, ppo_lstm, mlp_zoo, ppo_lstm_zoo",
        ),
        (("TMazeCue-v0", "ppo", "hebb"), r"^unknown rule 'hebb'; accepted: static, "),
        (("HalfCheetah-v5", "mlp", "dp-oja"), r"^rule='dp-oja' needs policy SpikePlasticPolicy, not 'MlpPolicy'"),
    ],
)
def test_load_hyperparams_bad_input_is_one_line(args, message):
    with pytest.raises(ValueError, match=message) as info:
        load_hyperparams(*args)
    assert "\n" not in str(info.value)


def test_load_hyperparams_builds_and_trains_a_model():
    h = load_hyperparams("TMazeCue-v0", rule="dp-linear")
    env = DummyVecEnv([lambda: gym.make("TMazeCue-v0") for _ in range(2)])
    model = PPO(
        h.policy,
        env,
        **{**h.model_kwargs, "n_steps": 16, "batch_size": 16, "bptt_steps": 8, "n_epochs": 1},
        device="cpu",
        seed=0,
    )
    assert model.policy.snn.rule_name == "dp-linear" and model.policy.snn_config["alpha_lr_scale"] == 30
    assert model.use_action_masks is True and model.bptt_steps == 8
    model.learn(32)
    assert model.num_timesteps == 32
    env.close()


def test_packaged_paper_configuration():
    config = load_hyperparams_file("paper")["HalfCheetah-v5"]
    kwargs = config["policy_kwargs"]
    assert kwargs["obs_indices"] == [2, 3, 4, 5, 6, 7, 11, 12, 13, 14, 15, 16]
    assert (kwargs["encoder_pop_size"], kwargs["action_pop_size"], kwargs["steps"]) == (50, 100, 50)
    assert "hidden_sizes" not in kwargs and "n_epochs" not in config  # the defaults, 64-64 and 10, are the paper's
    assert config["n_steps"] * config["n_envs"] == 3000 and config["gae_lambda"] == 0.97
    assert config["learning_rate"] == "lin_5e-4"


def test_whole_mapping_override_names_the_keys_it_drops(tmp_path, capsys):
    lines = replaced_mappings("TMazeCue-v0", None, ["policy_kwargs=dict(hidden_sizes=[32], alpha_lr_scale=2)"])
    assert len(lines) == 1 and lines[0].startswith(
        "--hyperparams policy_kwargs=dict(hidden_sizes=[32], "
        "alpha_lr_scale=2) replaces the entry's whole policy_kwargs, "
    )
    dropped = lines[0].split("dropping its ")[1].split(" (")[0].split(", ")
    assert "alpha_init_mean" in dropped and "alpha_lr_scale" not in dropped  # the entry's, less those given
    # a dotted key keeps the others; a key set again by a later override is not dropped
    assert replaced_mappings("TMazeCue-v0", None, ["policy_kwargs.hidden_sizes=[32]"]) == []
    again = replaced_mappings(
        "TMazeCue-v0", None, ["policy_kwargs:{hidden_sizes: [32]}", "policy_kwargs.alpha_init_mean=0"]
    )
    assert "alpha_init_mean" not in again[0].split("dropping its ")[1]
    # the command line prints it once the command is checked and its model built, before the run
    argv = [
        "train",
        "--env",
        "HalfCheetah-v5",
        "-f",
        str(tmp_path),
        "--hyperparams",
        "policy_kwargs=dict(hidden_sizes=[16], steps=5)",
    ]
    cli.prepare(cli.build_parser().parse_args(argv), argv)
    out = capsys.readouterr().out
    assert (
        "sb3-spikeplastic: --hyperparams policy_kwargs=dict(hidden_sizes=[16], steps=5) replaces the entry's "
        "whole policy_kwargs, dropping its " in out
    )
    assert list(tmp_path.iterdir()) == []
