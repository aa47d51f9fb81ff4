import subprocess
import sys
from pathlib import Path

import pytest
from dvc.utils.serialize import parse_yaml

from carp.config import ConfigError, Params, flatten_params, load_params, params_from_dict, params_to_dict

REPO = Path(__file__).resolve().parents[1]


def test_repository_params_load_and_match_defaults_shape():
    params = load_params(REPO / "params.yaml")
    assert params.scales[-1] == params.latent_length == 4
    assert params.codebook_size >= 2
    assert params.action_space == "panda-abs10"
    assert params.action_format.policy_dim == 10


def test_params_yaml_states_exactly_the_config_defaults():
    # One home per default: the dataclasses. params.yaml spells every key out for users and must not drift from them.
    written = flatten_params(params_from_dict(parse_yaml((REPO / "params.yaml").read_text(), "params.yaml")))
    defaults = flatten_params(Params())
    assert set(written) == set(defaults)
    assert {key: (value, defaults[key]) for key, value in written.items() if defaults[key] != value} == {}


def test_defaults_follow_the_design():
    params = Params()
    assert params.scales == (1, 2, 3, 4)
    assert params.codebook_size == 512
    assert params.tasks == ("lift",)
    assert (params.data.obs_steps, params.data.action_horizon, params.data.action_steps) == (2, 16, 8)
    assert params.policies == ("carp",)
    assert params.multitask == ()
    assert (params.register, params.tracking.policy_alias) == ((), "candidate")
    carp = params.family_config("carp")
    assert (carp.depth, carp.width, carp.num_heads) == (8, 64, 8)
    assert params.tokenizer.latent_channels == 8


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ({"scales": [1, 2, 17]}, "scales=[1, 2, 17]: every schedule must be positive, strictly increasing and end at"),
        ({"scales": [1, 3, 2, 4]}, "scales=[1, 3, 2, 4]: every schedule must be positive, strictly increasing"),
        ({"codebook_size": 1}, "codebook_size=1: must be >= 2"),
        ({"tasks": ["peg_in_hole"]}, "tasks=['peg_in_hole']: 'peg_in_hole' is not a registered task"),
        ({"tasks": []}, "tasks=(): must list at least one task"),
        ({"data": {"action_horizon": 10}}, "data.action_horizon=10: must be divisible by"),
        ({"data": {"controller": "joint"}}, "data.controller='joint': must be one of"),
        ({"data": {"action_steps": 16}}, "data.action_steps=16: must be between 1 and"),
        ({"carp": {"width": 64, "num_heads": 5}}, "carp.num_heads=5: must divide width=64"),
        ({"carp": {"depth": "deep"}}, "carp.depth='deep': expected an integer"),
        ({"carp": {"use_ema": "yes"}}, "carp.use_ema='yes': expected true or false"),
        ({"carp": {"learning_rate": 0}}, "carp.learning_rate=0.0: must be > 0"),
        ({"tokenizer": {"source": "mlflow://x"}}, "tokenizer.source='mlflow://x': must be 'pipeline' or"),
        ({"tokenizer": {"registry_alias": "latest"}}, "tokenizer.registry_alias='latest'"),
        ({"eval": {"episodes": 0}}, "eval.episodes=0: must be >= 1"),
        ({"eval": {"backend": "tensorrt"}}, "eval.backend='tensorrt': must be one of"),
        ({"training": {"precision": "half"}}, "training.precision='half': must be one of"),
        ({"training": {"epochs_per_task": {"kitchen": 5}}}, "training.epochs_per_task.kitchen='kitchen': task must"),
        ({"training": {"epochs_per_task": {"square": 0}}}, "training.epochs_per_task.square=0: must be >= 1"),
        ({"training": {"num_processes": 0}}, "training.num_processes=0: must be >= 1"),
        ({"training": {"num_processes": 1.5}}, "training.num_processes=1.5: "),
        ({"training": {"batch_size": 4, "num_processes": 8}}, "training.num_processes=8: must be <= batch_size=4"),
        (
            {"inference": {"carp": {"top_k_per_task": {"kitchen": 3}}}},
            "inference.carp.top_k_per_task.kitchen='kitchen'",
        ),
        ({"inference": {"carp": {"top_k_per_task": {"can": 0}}}}, "inference.carp.top_k_per_task.can=0: must be >= 1"),
        (
            {"inference": {"carp": {"top_k_per_task": {"can": 9}}}, "codebook_size": 8},
            "inference.carp.top_k_per_task.can=9: must be <= codebook_size = 8",
        ),
        ({"inference": {"carp": {"top_k": 600}}}, "inference.carp.top_k=600: must be <= codebook_size = 512"),
        (
            {"tasks": ["pusht"], "data": {"controller": "delta"}},
            "data.controller='delta': pusht: controller 'delta': the agent takes absolute targets only",
        ),
        (
            {"tasks": ["lift", "pusht"]},
            "tasks=['lift', 'pusht']: tasks must share one action space (one tokenizer serves them all), "
            "got {'lift': 'panda-abs10', 'pusht': 'pusht-abs2'}",
        ),
        (
            {"tasks": ["pusht"], "data": {"observations": "image"}},
            "data.observations='image': pusht has no camera observations; use state",
        ),
        ({"sweep": {"scale_schedules": [[2, 1]]}}, "sweep.scale_schedules=[[2, 1]]: every schedule"),
        ({"sweep": {"git_remote": "--force"}}, "sweep.git_remote='--force': must be a git remote name or URL"),
        ({"sweep": {"pruner": "median"}}, "sweep.pruner='median': must be one of ('successive_halving', 'hyperband',"),
        ({"sweep": {"confirm_seeds": [0]}}, "sweep.confirm_seeds=[0]: must hold at least two distinct integer seeds"),
        ({"sweep": {"confirm_seeds": [1, 1]}}, "sweep.confirm_seeds=[1, 1]: must hold at least two distinct"),
        ({"eval": {"run_test": False}}, "eval.run_test=False: false needs validation episodes"),
        (
            {"eval": {"run_test": False, "validation_episodes": 2, "selection": "average_last"}},
            "eval.run_test=False: false needs a rule that selects one validated candidate",
        ),
        ({"sweep": {"git_remote": " origin"}}, "sweep.git_remote=' origin': must be a git remote name or URL"),
        ({"carp": {"depht": 3}}, "carp.depht: unknown key"),
        ({"policy": {"depth": 3}}, "policy: unknown key (known: carp, codebook_size,"),
        (
            {"policies": ["carp", "lstm"]},
            "policies=['carp', 'lstm']: every family must be one of ['carp', 'diffusion_unet',",
        ),
        ({"policies": ["carp", "carp"]}, "policies=('carp', 'carp'): must not repeat a family"),
        ({"policies": []}, "policies=[]: must list at least one policy family (empty only when multitask lists one)"),
        (
            {"tasks": ["can", "square"], "multitask": ["carp", "lstm"]},
            "multitask=['carp', 'lstm']: every family must be one of ['carp', 'diffusion_unet',",
        ),
        (
            {"tasks": ["can", "square"], "multitask": ["carp", "carp"]},
            "multitask=['carp', 'carp']: must not repeat a family",
        ),
        (
            {"tasks": ["can"], "multitask": ["carp"]},
            "multitask=['carp']: a multi-task policy needs at least two tasks, tasks=['can']",
        ),
        (
            {"tasks": ["can", "square"], "multitask": ["carp"], "data": {"observations": "image"}},
            "multitask=['carp']: multi-task policies train on state observations, data.observations='image'",
        ),
        (
            {"tasks": ["can", "square"], "multitask": ["carp", "consistency_policy"]},
            "multitask=['carp', 'consistency_policy']: consistency_policy distils its edm_unet teacher, which trains "
            "on one task only",
        ),
        (
            {"tasks": ["lift", "pusht"], "multitask": ["carp"]},
            "tasks=['lift', 'pusht']: tasks must share one action space",
        ),
        (
            {"register": ["carp", "lstm"]},
            "register=['carp', 'lstm']: every family must be one of ['carp', 'diffusion_unet',",
        ),
        (
            {"policies": ["carp"], "register": ["next_token"]},
            "register=['next_token']: every family must also be in policies=['carp'] (the pipeline registers what "
            "it trains)",
        ),
        ({"register": ["carp", "carp"]}, "register=['carp', 'carp']: must not repeat a family"),
        ({"tracking": {"policy_alias": ""}}, "tracking.policy_alias='': must be set"),
        ({"tracking": {"policy_alias": "Latest"}}, "tracking.policy_alias='Latest': 'latest', 'v<digits>' and names"),
        ({"tracking": {"policy_alias": "2nd"}}, "tracking.policy_alias='2nd': 'latest', 'v<digits>' and names"),
        ({"tracking": {"policy_alias": "v3"}}, "tracking.policy_alias='v3': 'latest', 'v<digits>' and names"),
        ({"tracking": {"policy_alias": "my pick"}}, "tracking.policy_alias='my pick': may only contain letters,"),
        ({"lstm": {"depth": 3}}, "lstm: unknown key"),
        (
            {"inference": {"lstm": {}}},
            "inference.lstm: unknown policy family (known: carp, diffusion_unet, diffusion_transformer, next_token, "
            "vq_bet, edm_unet, consistency_policy)",
        ),
        ({"inference": {"carp": {"top_p": 0.9}}}, "inference.carp.top_p: unknown key (known: top_k, top_k_per_task)"),
        ({"eval": {"seed": 100}, "data": {"num_demos": 50}}, "eval.seed=100: evaluation seeds [100, 150) overlap"),
        ({"data": {"num_demos_per_task": {"kitchen": 5}}}, "data.num_demos_per_task.kitchen='kitchen': task must be"),
        ({"data": {"num_demos_per_task": {"lift": 0}}}, "data.num_demos_per_task.lift=0: must be at least 1"),
        (
            {"eval": {"seed": 400}, "data": {"num_demos": 50, "num_demos_per_task": {"lift": 200}}},
            "eval.seed=400: evaluation seeds [400, 450) overlap the collection seeds [0, 600)",
        ),
        ({"tokenizer": {"tasks": ["can"]}}, "tokenizer.tasks=['can']: every tokenizer task must also be in tasks"),
        ({"colour": "red"}, "colour: unknown key"),
        ({"seeds": []}, "seeds=[]: must list at least one training seed"),
        ({"seeds": [0, 0]}, "seeds=[0, 0]: must not repeat a seed"),
        ({"seeds": [-1]}, "seeds=[-1]: every seed must be >= 0"),
        (
            {"training": {"seed": 3}},
            "training.seed=3: set by the pipeline for each run, not in params.yaml (training seeds",
        ),
        ({"training": {"snapshot_every": -1}}, "training.snapshot_every=-1: must be >= 0"),
        ({"eval": {"selection": "best"}}, "eval.selection='best': must be one of ('final', 'best_validation',"),
        ({"eval": {"selection": "best_validation"}}, "eval.validation_episodes=0: must be >= 1 with selection"),
        ({"eval": {"average_last": 0}}, "eval.average_last=0: must be an integer >= 1"),
        ({"carp": {"attention": "flash"}}, "carp.attention='flash': must be one of ('auto', 'masked', 'blockwise')"),
        (
            {"eval": {"validation_seed": 100_040, "validation_episodes": 20}},
            "eval.validation_seed=100040: validation seeds [100040, 100060) overlap the test seeds [100000, 100050)",
        ),
        (
            {"eval": {"validation_seed": 250, "validation_episodes": 20}},
            "eval.validation_seed=250: validation seeds [250, 270) overlap the collection seeds [0, 300)",
        ),
        ({"data": {"subset_size": 150}}, "data.subset_size=150: must be <= the 100 demos collected for lift"),
        ({"study": {"data_efficiency_sizes": [60, 30]}}, "study.data_efficiency_sizes=[60, 30]: must hold at least"),
        ({"eval": {"ensemble_m": -1}}, "eval.ensemble_m=-1.0: must be null or a number >= 0"),
        ({"comparison": {"margin": 0}}, "comparison.margin=0.0: must lie in (0, 1)"),
        ({"comparison": {"alpha": 0.5}}, "comparison.alpha=0.5: must lie in (0, 0.5)"),
        ({"comparison": {"references": ["a", "a"]}}, "comparison.references=['a', 'a']: must name each once"),
        ({"comparison": {"references": [""]}}, "comparison.references=['']: must be non-empty paths"),
        ({"serving": {"max_batch": 0}}, "serving.max_batch=0: must be an integer >= 1"),
        ({"serving": {"prediction_threads": -1}}, "serving.prediction_threads=-1: must be an integer >= 0"),
        ({"data": [1, 2]}, "data: expected a mapping"),
        ({"data": {"observations": "depth"}}, "data.observations='depth': must be one of ('state', 'image')"),
        ({"data": {"cameras": []}}, "data.cameras=[]: must name at least one camera"),
        ({"data": {"cameras": ["agentview", ""]}}, "data.cameras=['agentview', '']: camera names must not be empty"),
        (
            {"data": {"cameras": ["agentview", "agentview"]}},
            "data.cameras=['agentview', 'agentview']: must name each camera once",
        ),
        ({"data": {"cameras": "agentview"}}, "data.cameras='agentview': expected a list"),
        ({"data": {"image_size": 0}}, "data.image_size=0: must be an integer >= 1"),
        ({"data": {"image_size": 84.5}}, "data.image_size=84.5: expected an integer"),
        ({"data": {"render_workers": -1}}, "data.render_workers=-1: must be an integer >= 0"),
        ({"data": {"proprioception_keys": []}}, "data.proprioception_keys=[]: must name at least one key"),
        (
            {"data": {"proprioception_keys": ["robot0_eef_pos", "agentview_image"]}},
            "data.proprioception_keys=['robot0_eef_pos', 'agentview_image']: must be low-dim keys, not camera images",
        ),
    ],
)
def test_bad_values_are_refused_with_the_key_named(raw, message):
    with pytest.raises(ConfigError) as error:
        params_from_dict(raw)
    assert message in str(error.value)


def test_image_observations_swap_the_object_pose_for_proprioception_and_cameras():
    state = Params().data
    assert state.observations == "state" and state.image_keys == () and state.low_dim_keys == state.obs_keys
    image_params = params_from_dict(
        {
            "data": {"observations": "image", "cameras": ["agentview"], "image_size": 64},
            "image_encoder": {"crop_size": 56},
        }
    )
    image = image_params.data
    assert image.image_keys == ("agentview_image",) and image.image_size == 64
    assert image.low_dim_keys == ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
    assert "object" in state.low_dim_keys and "object" not in image.low_dim_keys
    # The policies' camera encoder sees what ingest stored; state policies have none.
    encoder = image_params.policy_image_encoder
    assert encoder.cameras == ("agentview",) and encoder.image_size == 64 and encoder.crop_size == 56
    assert Params().policy_image_encoder is None


def test_the_image_encoder_section_takes_its_cameras_and_size_from_data():
    with pytest.raises(ConfigError, match=r"image_encoder.crop_size=76: must be an integer in \[1, image_size=64\]"):
        params_from_dict({"data": {"observations": "image", "image_size": 64}})
    with pytest.raises(ConfigError, match=r"image_encoder.cameras=\['agentview'\]: is data.cameras; set data.cameras"):
        params_from_dict({"image_encoder": {"cameras": ["agentview"]}})
    with pytest.raises(ConfigError, match="image_encoder.image_size=100: is data.image_size; set data.image_size"):
        params_from_dict({"image_encoder": {"image_size": 100}})
    # Restating data's values is allowed; a state run ignores the encoder's crop.
    same = {"cameras": ["agentview"], "image_size": 40, "crop_size": 36}
    assert params_from_dict({"data": {"cameras": ["agentview"], "image_size": 40}, "image_encoder": same})
    assert params_from_dict({"data": {"image_size": 40}}).policy_image_encoder is None


def test_load_params_names_the_file(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("codebook_size: 1\n")
    with pytest.raises(ConfigError, match=r"params.yaml: codebook_size=1"):
        load_params(path)
    with pytest.raises(ConfigError, match="params file not found"):
        load_params(tmp_path / "missing.yaml")
    path.write_text("scales: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params(path)


def test_params_are_frozen_and_flatten():
    params = params_from_dict({"scales": [1, 2, 4], "codebook_size": 256})
    assert params.scales == (1, 2, 4)
    with pytest.raises(AttributeError):
        params.codebook_size = 3  # type: ignore[misc]
    flat = flatten_params(params)
    assert flat["codebook_size"] == "256"
    assert flat["carp.depth"] == "8" and flat["inference.carp.top_k"] == "1" and flat["training.epochs"] == "20"
    assert flat["scales"] == "[1, 2, 4]"
    # The training seed is each run's own (a tag of its stage's run), not a param of the file.
    assert "training.seed" not in flat and flat["seeds"] == "[0]"


def test_params_round_trip_through_the_files_shape():
    params = params_from_dict({"seeds": [0, 2], "policies": ["carp", "next_token"], "next_token": {"depth": 2}})
    assert params_from_dict(params_to_dict(params)) == params


def test_each_training_seed_gets_its_own_training_settings():
    params = params_from_dict({"seeds": [0, 3], "eval": {"validation_episodes": 10}})
    assert [params.training_for_seed(seed).seed for seed in params.seeds] == [0, 3]
    assert params.training_for_seed(3).epochs == params.training.epochs
    assert params.eval.validation_seeds()[:2] == [200_000, 200_001] and len(params.eval.validation_seeds()) == 10
    assert params.eval.test_seeds() == list(range(100_000, 100_050))


def test_policy_epochs_per_task_override_the_common_value():
    params = params_from_dict(
        {"tasks": ["lift", "square"], "training": {"epochs": 20, "epochs_per_task": {"square": 35}}}
    )
    assert params.training.epochs_for("square", "carp") == 35
    assert params.training.epochs_for("lift", "carp") == 20
    assert flatten_params(params)["training.epochs_per_task.square"] == "35"


def test_policy_epochs_per_family_override_the_task_and_common_values():
    training = {"epochs": 40, "epochs_per_task": {"square": 60}, "epochs_per_policy": {"diffusion_unet": 120}}
    params = params_from_dict({"tasks": ["lift", "square"], "training": training})
    assert [params.training.epochs_for(task, "diffusion_unet") for task in params.tasks] == [120, 120]
    assert [params.training.epochs_for(task, "carp") for task in params.tasks] == [40, 60]
    with pytest.raises(ConfigError, match=r"training.epochs_per_policy.diffusion='diffusion': family must be one of"):
        params_from_dict({"training": {"epochs_per_policy": {"diffusion": 100}}})
    with pytest.raises(ConfigError, match=r"training.epochs_per_policy.carp=0: must be an integer >= 1"):
        params_from_dict({"training": {"epochs_per_policy": {"carp": 0}}})


def test_num_demos_per_task_overrides_the_common_demo_count():
    params = params_from_dict(
        {"tasks": ["lift", "square"], "data": {"num_demos": 200, "num_demos_per_task": {"square": 300}}}
    )
    assert [params.data.demos_for(task) for task in params.tasks] == [200, 300]
    assert flatten_params(params)["data.num_demos_per_task.square"] == "300"
    # A task outside `tasks` is never collected, so its count does not move the collection seeds.
    assert params_from_dict({"eval": {"seed": 400}, "data": {"num_demos_per_task": {"can": 200}}}).eval.seed == 400


def test_policy_top_k_per_task_overrides_the_common_token_choice():
    params = params_from_dict(
        {
            "tasks": ["lift", "can", "square"],
            "inference": {"carp": {"top_k": 3, "top_k_per_task": {"can": 5, "square": 1}}},
        }
    )
    assert [params.inference_settings("carp", task) for task in params.tasks] == [{"top_k": k} for k in (3, 5, 1)]
    assert flatten_params(params)["inference.carp.top_k_per_task.can"] == "5"


@pytest.mark.parametrize("text, expected", [("1e-3", 0.001), ("1E5", 100000.0), ("+1e-3", 0.001), ("2.5E-2", 0.025)])
def test_numbers_read_as_dvc_reads_them(tmp_path, text, expected):
    path = tmp_path / "params.yaml"
    path.write_text(f"carp:\n  learning_rate: {text}\n")
    assert load_params(path).family_config("carp").learning_rate == expected
    dvc_value = parse_yaml(path.read_text(), str(path))["carp"]["learning_rate"]
    assert dvc_value == expected


def test_values_dvc_reads_as_strings_or_refuses_are_refused(tmp_path):
    path = tmp_path / "params.yaml"
    # YAML 1.2 (DVC) reads `yes` as a string; YAML 1.1 would have made it true.
    path.write_text("carp:\n  use_ema: yes\n")
    with pytest.raises(ConfigError, match=r"carp.use_ema='yes': expected true or false"):
        load_params(path)
    path.write_text("codebook_size: 64\ncodebook_size: 128\n")
    with pytest.raises(ConfigError, match=r"params.yaml: not valid YAML \(found duplicate key \"codebook_size\""):
        load_params(path)


def test_loading_params_imports_no_model_code():
    """Every stage, the always-run input check included, loads params first: the families' sections come from their
    light config modules, not from torch and the networks, and the tasks' facts from their modules, not from the
    simulators."""
    code = (
        "import sys; from carp.config import load_params; params = load_params('params.yaml'); "
        "assert set(params.families) >= {'carp', 'diffusion_unet', 'diffusion_transformer', 'next_token'}; "
        "heavy = ('torch', 'diffusers', 'scipy', 'robosuite', 'mujoco', 'gym_pusht', 'pymunk'); "
        "print(sorted(name for name in heavy if name in sys.modules))"
    )
    completed = subprocess.run(
        [sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    assert completed.stdout.strip() == "[]"


def test_each_task_gets_its_action_format_observation_keys_and_step_limit():
    arms = params_from_dict({"tasks": ["lift", "can"], "eval": {"max_steps": {"lift": 250}}})
    assert arms.action_space == "panda-abs10" and arms.action_format.stored_dim == 7
    assert arms.max_steps_for("lift") == 250 and arms.max_steps_for("can") == 400  # no entry: the task's default
    assert arms.obs_keys_for("can") == arms.data.obs_keys
    delta = params_from_dict({"data": {"controller": "delta"}})
    assert delta.action_space == "panda-delta7" and delta.action_format.policy_dim == 7
    pusht = params_from_dict({"tasks": ["pusht"], "data": {"obs_keys": ["object"]}})
    assert pusht.action_space == "pusht-abs2"
    assert pusht.action_format.stored_dim == pusht.action_format.policy_dim == 2
    assert pusht.obs_keys_for("pusht") == ("block_keypoints", "agent_pos")  # Push-T's observation is fixed
    assert pusht.max_steps_for("pusht") == 300


def test_multitask_families_need_not_be_single_task_families():
    params = params_from_dict({"tasks": ["can", "square"], "policies": ["carp"], "multitask": ["diffusion_unet"]})
    assert params.multitask == ("diffusion_unet",)
    assert params.family_config("diffusion_unet") is not None
    # A run of multi-task policies alone: no single-task family.
    alone = params_from_dict({"tasks": ["can", "square"], "policies": [], "multitask": ["carp"]})
    assert alone.policies == () and alone.multitask == ("carp",)


def test_registered_families_are_a_subset_of_the_trained_ones_with_a_hyphenated_alias():
    params = params_from_dict(
        {"policies": ["carp", "next_token"], "register": ["next_token"], "tracking": {"policy_alias": "pick_2-a"}}
    )
    assert params.register == ("next_token",) and params.tracking.policy_alias == "pick_2-a"


LEROBOT_V3 = str(REPO / "tests" / "fixtures" / "lerobot" / "v3.0")


def test_a_task_carp_does_not_know_is_a_task_without_a_simulator_described_by_its_lerobot_dataset():
    params = params_from_dict({"tasks": ["my_robot"], "data": {"raw_files": {"my_robot": LEROBOT_V3}}})
    assert params.task("my_robot").evaluation == "offline" and params.task("lift").evaluation == "rollouts"
    assert params.action_space == "pusht-abs2" and params.action_format.dimension_names == ("x", "y")
    # The dataset's low-dim observation features, whatever data.obs_keys says.
    assert params.obs_keys_for("my_robot") == ("state", "environment_state")


def test_per_task_settings_accept_a_task_without_a_simulator_that_tasks_lists():
    overrides = {"my_robot": 3}
    params = params_from_dict(
        {
            "tasks": ["my_robot"],
            "data": {"raw_files": {"my_robot": LEROBOT_V3}, "num_demos_per_task": overrides},
            "training": {"epochs_per_task": overrides},
            "eval": {"max_steps": overrides},
            "tokenizer": {"tasks": ["my_robot"]},
            "inference": {"carp": {"top_k_per_task": overrides}},
        }
    )
    assert params.training.epochs_for("my_robot", "carp") == 3 and params.tokenizer_tasks == ("my_robot",)
    with pytest.raises(ConfigError, match=r"eval.max_steps.robot2='robot2': task must be a registered one \["):
        params_from_dict(
            {
                "tasks": ["my_robot"],
                "data": {"raw_files": {"my_robot": LEROBOT_V3}},
                "eval": {"max_steps": {"robot2": 5}},
            }
        )


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ({"tasks": ["lfit"]}, "tasks=['lfit']: 'lfit' is not a registered task ["),
        (
            {"tasks": ["my_robot"], "data": {"raw_files": {"my_robot": str(REPO / "params.yaml")}}},
            "data.raw_files.my_robot='",
        ),
        ({"data": {"raw_files": {"lfit": "own/lift.hdf5"}}}, "data.raw_files.lfit='own/lift.hdf5': 'lfit' is not a"),
        (
            {"tasks": ["lift", "my_robot"], "data": {"raw_files": {"my_robot": LEROBOT_V3}}},
            "tasks must share one action space",
        ),
        (
            {"tasks": ["my_robot"], "data": {"observations": "image", "raw_files": {"my_robot": LEROBOT_V3}}},
            "my_robot has no camera observations",
        ),
    ],
)
def test_a_typo_or_a_task_without_a_usable_dataset_is_refused_naming_the_key(raw, message):
    with pytest.raises(ConfigError) as error:
        params_from_dict(raw)
    assert message in str(error.value)


def test_a_typod_task_stops_the_pipeline_with_one_error_line_naming_the_file(tmp_path):
    params_file = tmp_path / "params.yaml"
    params_file.write_text("tasks: [lfit]\n")
    completed = subprocess.run(
        [sys.executable, "pipeline/check_inputs.py", "--params", str(params_file)],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert completed.returncode == 1
    assert completed.stderr.splitlines() == [
        f"error: {params_file}: tasks=['lfit']: 'lfit' is not a registered task ['lift', 'can', 'square', 'stack', "
        "'nut_assembly', 'stack_three', 'threading', 'pusht'], and data.raw_files.lfit names no LeRobotDataset folder "
        "for a task without a simulator"
    ]
