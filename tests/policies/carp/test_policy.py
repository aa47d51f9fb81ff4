from dataclasses import replace

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.sampling import generate_chunk
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.checkpoint import CheckpointError
from tests.policies.carp.factories import (
    OBS_DIM,
    OBS_STEPS,
    scrambled_transformer,
    tiny_artifact,
    tiny_policy,
    tiny_policy_spec,
    tiny_tokenizer,
    tiny_tokenizer_spec,
)


def _raw_obs(policy: CarpPolicy, batch: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    low, high = policy.obs_normalizer.minimum, policy.obs_normalizer.maximum
    return rng.uniform(low, high, size=(batch, OBS_STEPS, OBS_DIM)).astype(np.float32)


def test_predict_action_normalizes_predicts_decodes_and_unnormalizes():
    policy = tiny_policy()
    obs = _raw_obs(policy, 4)
    actions = policy.predict_action(obs)
    assert actions.shape == (4, 8, 2) and actions.dtype == np.float32
    with torch.inference_mode():
        normalized_obs = policy.obs_normalizer.normalize(torch.from_numpy(obs))
        chunk = generate_chunk(policy.transformer, policy.tokenizer, normalized_obs)
        expected = policy.action_normalizer.unnormalize(policy.tokenizer.decode_latent(chunk.latent))
    np.testing.assert_allclose(actions, expected.numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(policy.predict_action(torch.from_numpy(obs)), actions)


def test_timed_prediction_reports_both_durations():
    policy = tiny_policy()
    timed = policy.predict_action_timed(_raw_obs(policy, 1))
    assert timed.actions.shape == (1, 8, 2)
    assert 0 < timed.prediction_seconds < 5 and 0 < timed.decoding_seconds < 5
    assert 0 < timed.encoding_seconds < timed.prediction_seconds  # a state policy's encoding is only the normalization
    assert timed.model_calls == len(policy.spec.scales)
    assert timed.repaired_chunks is None  # CARP's tokens always decode as they are


def test_save_load_round_trip_gives_identical_actions(tmp_path):
    policy = tiny_policy(num_tasks=2)
    obs = _raw_obs(policy, 3)
    path = tmp_path / "policy" / "policy.pt"
    policy.save(path)
    loaded = CarpPolicy.load(path)
    assert loaded.spec == policy.spec
    assert loaded.tokenizer.spec == policy.tokenizer.spec
    assert loaded.metadata == policy.metadata
    assert loaded.metadata["tokenizer_ref"] == {"name": "carp-tokenizer-test", "version": 1}
    assert loaded.tasks.to_dict() == policy.tasks.to_dict() and loaded.tasks.names == ("task0", "task1")
    np.testing.assert_array_equal(loaded.obs_normalizer.minimum, policy.obs_normalizer.minimum)
    for task in (0, 1):
        np.testing.assert_array_equal(loaded.predict_action(obs, task), policy.predict_action(obs, task))
    sampled = [
        model.predict_action(obs, 1, top_k=3, generator=torch.Generator().manual_seed(7)) for model in (policy, loaded)
    ]
    np.testing.assert_array_equal(*sampled)
    assert [file.name for file in path.parent.iterdir()] == ["policy.pt"]


def test_loading_is_strict(tmp_path):
    policy = tiny_policy()
    checkpoint = policy.to_checkpoint()
    checkpoint["transformer_state"]["unexpected"] = torch.zeros(1)
    with pytest.raises(RuntimeError, match="Unexpected key"):
        CarpPolicy.from_checkpoint(checkpoint)
    with pytest.raises(ValueError, match="format_version 99"):
        CarpPolicy.from_checkpoint(policy.to_checkpoint() | {"format_version": 99})


def _save_changed(policy: CarpPolicy, path, change) -> None:
    checkpoint = policy.to_checkpoint()
    change(checkpoint)
    torch.save(checkpoint, path)


def test_a_tokenizer_of_the_same_shape_that_is_not_the_recorded_one_is_refused(tmp_path):
    policy = tiny_policy()
    other = tiny_artifact(tiny_tokenizer(seed=1))
    assert other.tokenizer.spec == policy.tokenizer.spec and other.sha256 != policy.tokenizer_artifact.sha256
    path = tmp_path / "policy.pt"
    _save_changed(policy, path, lambda checkpoint: checkpoint.update(tokenizer=other.to_payload()))
    with pytest.raises(CheckpointError) as raised:
        CarpPolicy.load(path)
    assert str(raised.value) == (
        f"{path}: tokenizer weights have sha256 {other.sha256[:12]}..., not the sha256 "
        f"{policy.tokenizer_artifact.sha256[:12]}... recorded in the policy (the tokenizer it was trained with)"
    )
    # Changed statistics of a training task change the tokenizer's identity as well.
    changed = policy.to_checkpoint()
    changed["tokenizer"]["action_normalizers"]["task"]["maximum"][0] = 4.0
    torch.save(changed, path)
    with pytest.raises(CheckpointError, match="recorded in the policy"):
        CarpPolicy.load(path)


def test_the_recorded_tokenizer_round_trips(tmp_path):
    policy = tiny_policy()
    policy.save(tmp_path / "policy.pt")
    loaded = CarpPolicy.load(tmp_path / "policy.pt")
    assert loaded.tokenizer_artifact.sha256 == policy.tokenizer_artifact.sha256
    assert loaded.tokenizer_artifact.tasks == ["task"] and loaded.tokenizer_artifact.action_space == "test-abs2"
    assert loaded.tokenizer_artifact.tokenizer is loaded.tokenizer


def _truncate(path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _other_codebook(checkpoint: dict) -> None:
    bigger = tiny_artifact(MultiScaleActionTokenizer(replace(tiny_tokenizer_spec(), codebook_size=16)))
    checkpoint.update(tokenizer=bigger.to_payload(), tokenizer_sha256=bigger.sha256)


DAMAGED_POLICIES = {
    "truncated": (_truncate, "not a readable checkpoint, truncated or corrupt ("),
    "tokenizer with another codebook size": (
        lambda path: _save_changed(tiny_policy(), path, _other_codebook),
        "policy spec does not match the tokenizer spec (codebook_size: policy 8 vs tokenizer 16)",
    ),
    "tokenizer weights of another size": (
        lambda path: _save_changed(
            tiny_policy(),
            path,
            lambda checkpoint: checkpoint["tokenizer"]["state_dict"].update(
                {"quantizer.codebook": torch.zeros(2, 16, 4)}
            ),
        ),
        "size mismatch for quantizer.codebook",
    ),
    "missing entry": (
        lambda path: _save_changed(tiny_policy(), path, lambda checkpoint: checkpoint.pop("tokenizer_sha256")),
        "policy checkpoint lacks the entry 'tokenizer_sha256'",
    ),
    "unknown policy type": (
        lambda path: _save_changed(tiny_policy(), path, lambda checkpoint: checkpoint.update(policy_type="lstm")),
        "policy_type='lstm': not a carp checkpoint",
    ),
    "another format version": (
        lambda path: _save_changed(tiny_policy(), path, lambda checkpoint: checkpoint.update(format_version=1)),
        "policy checkpoint has format_version 1, this code reads version 3",
    ),
}


@pytest.mark.parametrize("damage", list(DAMAGED_POLICIES))
def test_a_damaged_checkpoint_is_one_clear_error_naming_the_file(tmp_path, damage):
    path = tmp_path / "policy.pt"
    tiny_policy().save(path)
    change, expected = DAMAGED_POLICIES[damage]
    change(path)
    with pytest.raises(CheckpointError) as raised:
        CarpPolicy.load(path)
    message = str(raised.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message, message


def test_a_multi_task_checkpoint_keeps_the_selected_task_and_refuses_others(tmp_path):
    policy = tiny_policy(num_tasks=2)
    obs = _raw_obs(policy, 2)
    first = policy.predict_action(obs)
    np.testing.assert_array_equal(first, policy.predict_action(obs, 0))
    policy.select_task("task1")
    # Task 1's statistics are task 0's shifted by one: its own observations give its own actions.
    np.testing.assert_allclose(policy.obs_normalizer.minimum, policy.tasks.obs_normalizers["task0"].minimum + 1)
    np.testing.assert_array_equal(policy.predict_action(obs), policy.predict_action(obs, 1))
    policy.save(tmp_path / "policy.pt")
    loaded = CarpPolicy.load(tmp_path / "policy.pt")
    assert loaded.tasks.selected == "task1"
    np.testing.assert_array_equal(loaded.predict_action(obs), policy.predict_action(obs))
    with pytest.raises(ValueError, match="trained on tasks \\['task0', 'task1'\\], not on 'square'"):
        loaded.select_task("square")
    single = tiny_policy()
    single.metadata["task"] = "lift"
    single.select_task("lift")
    with pytest.raises(ValueError, match="trained on task 'lift', not on 'can'"):
        single.select_task("can")


def test_task_index_broadcasts_and_is_checked():
    policy = tiny_policy(num_tasks=3)
    obs = _raw_obs(policy, 2)
    np.testing.assert_array_equal(policy.predict_action(obs, 2), policy.predict_action(obs, np.array([2, 2])))
    assert not np.array_equal(policy.predict_action(obs, 0), policy.predict_action(obs, 2))
    with pytest.raises(ValueError, match="task indices must be in \\[0, 3\\)"):
        policy.predict_action(obs, 3)
    with pytest.raises(ValueError, match="one index or one per sample \\(2\\)"):
        policy.predict_action(obs, [0, 1, 2])


def test_bad_observations_are_rejected():
    policy = tiny_policy()
    with pytest.raises(ValueError, match="obs must have shape \\(B, To, Do\\) = \\(B, 2, 3\\), got \\(2, 3\\)"):
        policy.predict_action(np.zeros((2, 3)))


def test_parts_must_fit_together():
    tokenizer = tiny_artifact(tiny_tokenizer((1, 2)))
    normalizers = (MinMaxNormalizer(np.zeros(OBS_DIM), np.ones(OBS_DIM)), MinMaxNormalizer(np.zeros(2), np.ones(2)))
    with pytest.raises(ValueError, match="codebook_size: policy 16 vs tokenizer 8"):
        CarpPolicy(tokenizer, scrambled_transformer(tiny_policy_spec(codebook_size=16)), *normalizers)
    with pytest.raises(ValueError, match="obs normalizer has 4 features, the policy expects Do = 3"):
        CarpPolicy(
            tokenizer,
            scrambled_transformer(tiny_policy_spec()),
            MinMaxNormalizer(np.zeros(4), np.ones(4)),
            normalizers[1],
        )


def test_tokenizer_stays_frozen_in_train_mode():
    policy = tiny_policy().train()
    assert policy.transformer.training and not policy.tokenizer.training
    assert not any(parameter.requires_grad for parameter in policy.tokenizer.parameters())


def test_batch_of_envs_equals_one_by_one():
    policy = tiny_policy()
    obs = _raw_obs(policy, 3)
    batched = policy.predict_action(obs)
    for index in range(3):
        np.testing.assert_allclose(policy.predict_action(obs[index : index + 1]), batched[index : index + 1], atol=1e-5)


def test_training_loss_and_accuracy_sums_are_those_of_the_plain_teacher_forced_forward():
    from carp.policies.carp.trainer import compute_token_targets, teacher_forced_step

    policy = tiny_policy()
    generator = torch.Generator().manual_seed(0)
    batch = {
        "obs": torch.rand(6, 2, 3, generator=generator),
        "actions": torch.rand(6, 8, 2, generator=generator) * 2 - 1,
    }
    targets = compute_token_targets(policy.tokenizer, batch["actions"])
    logits = policy.transformer(batch["obs"], targets.teacher_inputs)  # (6, L, V) in sequence order
    expected_loss = torch.nn.functional.cross_entropy(logits.flatten(0, 1), targets.token_sequence.flatten())
    correct = (logits.argmax(dim=-1) == targets.token_sequence).double()  # (6, L)
    step = teacher_forced_step(
        policy.transformer,
        batch | {"token_sequence": targets.token_sequence, "teacher_inputs": targets.teacher_inputs},
    )
    torch.testing.assert_close(step.loss, expected_loss)
    torch.testing.assert_close(policy.training_loss(batch), expected_loss)
    # Sums over the six windows of each window's fraction of right tokens: in all, at scale 1 (A * s_1 = 2 tokens)
    # and at scale 2 (4 tokens).
    assert 0.0 < float(correct.mean()) < 1.0  # the scrambled weights get some tokens right, not all
    torch.testing.assert_close(step.metric_sums["token_accuracy"], correct.mean(dim=1).sum())
    torch.testing.assert_close(step.metric_sums["token_accuracy_scale_1"], correct[:, :2].mean(dim=1).sum())
    torch.testing.assert_close(step.metric_sums["token_accuracy_scale_2"], correct[:, 2:].mean(dim=1).sum())
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the tokens do not depend on the loop's autocast
        assert torch.isfinite(policy.training_loss(batch))
