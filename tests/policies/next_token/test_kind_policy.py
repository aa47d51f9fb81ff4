"""The next-token family over a fixed-length kind (binning) and a variable-length one (FAST) on synthetic chunks."""

import dataclasses

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import count_parameters
from carp.policies.context import MsvqLayout, PolicyContext
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.family import FAMILY, build
from carp.policies.next_token.generation import generate_sequences
from carp.policies.next_token.kind_policy import IGNORED, KindSequence, NextTokenKindPolicy
from carp.policies.next_token.matched_size import msvq_parameters, width_nearest
from carp.policies.registry import load_policy
from carp.tokenizer.artifact import TokenizerMismatchError
from carp.tokenizer.kinds.artifact import load_kind_artifact, save_kind_artifact
from carp.tokenizer.kinds.base import PADDING_ID, TokenBatch
from tests.tokenizer.kinds.conftest import A, H, fitted, smooth_chunks

OBS_STEPS, OBS_DIM = 2, 4
TINY = NextTokenConfig(depth=1, width=16, num_heads=2, warmup_steps=2, match_size=False)
MSVQ = MsvqLayout(scales=(1, 2, 4), codebook_size=256)
ACTIONS = MinMaxNormalizer(minimum=np.full(A, -2.0), maximum=np.full(A, 2.0))
OBSERVATIONS = MinMaxNormalizer(minimum=np.full(OBS_DIM, -1.0), maximum=np.full(OBS_DIM, 1.0))


@pytest.fixture(scope="module")
def chunks() -> torch.Tensor:
    return smooth_chunks(120, seed=0)


@pytest.fixture(scope="module", params=["binning", "fast"])
def artifact(request, chunks, tmp_path_factory):
    directory = tmp_path_factory.mktemp(request.param) / "tokenizer"
    save_kind_artifact(directory, fitted(request.param, chunks), {"lift": ACTIONS}, "panda-test3")
    return load_kind_artifact(directory)


def _context(artifact, msvq_layout: MsvqLayout | None = None) -> PolicyContext:
    return PolicyContext(
        OBSERVATIONS,
        ACTIONS,
        OBS_STEPS,
        H,
        tokenizer_artifact=artifact,
        metadata={"task": "lift"},
        msvq_layout=msvq_layout,
    )


def _policy(artifact, seed: int = 0, scrambled: bool = True) -> NextTokenKindPolicy:
    torch.manual_seed(seed)
    policy = build(TINY, _context(artifact))
    if scrambled:  # the default initialization gives near-uniform logits: scrambled weights make varied choices
        with torch.no_grad():
            for parameter in policy.transformer.parameters():
                parameter.normal_(0.0, 0.3)
    return policy.eval()


def _obs(batch: int) -> torch.Tensor:
    return torch.rand(batch, OBS_STEPS, OBS_DIM, generator=torch.Generator().manual_seed(3)) * 2 - 1


def test_the_transformer_is_sized_by_the_kind_and_predicts_chunks(artifact):
    policy = _policy(artifact)
    sequence = KindSequence.of(artifact.tokenizer)
    variable = artifact.kind == "fast"
    assert sequence.variable_length is variable
    assert sequence.end_id == (artifact.tokenizer.vocabulary_size if variable else None)
    assert policy.transformer.sequence_length == sequence.max_tokens + int(variable)
    assert policy.transformer.codebook_size == artifact.tokenizer.vocabulary_size + int(variable)
    if not variable:  # a fixed-length kind's rows are all L tokens, every id in its vocabulary
        assert sequence.max_tokens == H * A
        tokens = generate_sequences(policy.transformer, policy.observation_features(_obs(2), OBS_STEPS), H * A)
        assert isinstance(tokens, TokenBatch) and tokens.lengths.tolist() == [H * A, H * A]
        assert int(tokens.ids.min()) >= 0 and int(tokens.ids.max()) < artifact.tokenizer.vocabulary_size
    timed = policy.predict_action_timed(_obs(5))
    assert timed.actions.shape == (5, H, A) and timed.actions.dtype == np.float32
    assert 1 <= timed.model_calls <= sequence.max_tokens
    assert timed.repaired_chunks == policy.repaired_chunks and policy.decoded_chunks == 5
    assert policy.model_calls_per_chunk == sequence.max_tokens


def test_targets_end_with_the_end_token_and_ignore_the_padding(artifact, chunks):
    sequence = KindSequence.of(artifact.tokenizer)
    tokens = artifact.tokenizer.encode(chunks[:8])
    targets = sequence.targets(tokens)
    assert targets.shape == (8, sequence.positions)
    for row, length in enumerate(tokens.lengths.tolist()):
        assert torch.equal(targets[row, :length], tokens.ids[row, :length])
        if sequence.variable_length:
            assert targets[row, length] == sequence.end_id
            assert (targets[row, length + 1 :] == IGNORED).all()
    inputs = sequence.inputs(targets)
    assert int(inputs.min()) >= 0 and int(inputs.max()) < sequence.output_size


def test_training_lowers_the_loss(artifact, chunks):
    policy = _policy(artifact, scrambled=False).train()
    batch = {"obs": _obs(32), "actions": chunks[:32]}
    optimizer = torch.optim.Adam(policy.transformer.parameters(), lr=1e-2)
    first = policy.training_loss(batch).item()
    assert first == pytest.approx(np.log(policy.sequence.output_size), rel=0.05)  # near-uniform at initialization
    for _ in range(30):
        optimizer.zero_grad()
        loss = policy.training_loss(batch)
        loss.backward()
        optimizer.step()
    assert loss.item() < 0.7 * first


def test_the_end_token_stops_generation_and_its_row_is_padded():
    torch.manual_seed(0)
    transformer = NextTokenKindPolicy.transformer_for(TINY, OBS_DIM, OBS_STEPS, _FixedVocabulary(7, 5, True))
    end_id = 7
    with torch.no_grad():
        transformer.head.bias.zero_()
        transformer.head.weight.zero_()
        transformer.head.bias[0, 0, 3] = 10.0  # every position picks token 3 ...
    calls = []
    original = transformer.next_token_logits

    def scripted(state, previous=None):
        logits = original(state, previous)
        calls.append(state.next_step)
        if state.next_step == 3:  # ... until the third token, where row 0 ends and row 1 goes on once more
            logits[0, end_id] = 100.0
        if state.next_step == 4:
            logits[1, end_id] = 100.0
        return logits

    transformer.next_token_logits = scripted
    tokens = generate_sequences(transformer.eval(), _obs(2), steps=5, end_id=end_id)
    assert tokens.lengths.tolist() == [2, 3]
    assert tokens.ids.tolist() == [[3, 3, PADDING_ID, PADDING_ID, PADDING_ID], [3, 3, 3, PADDING_ID, PADDING_ID]]
    assert calls == [1, 2, 3, 4]  # generation stopped once both rows had ended, before the fifth token


def test_a_sequence_the_kind_cannot_decode_is_repaired_and_counted(chunks, tmp_path):
    directory = tmp_path / "tokenizer"
    save_kind_artifact(directory, fitted("fast", chunks), {"lift": ACTIONS}, "panda-test3")
    policy = _policy(load_kind_artifact(directory))
    end_id = policy.sequence.end_id
    with torch.no_grad():  # the end token first: an empty sequence, no coefficient at all
        policy.transformer.head.bias[0, 0, end_id] = 1e4
    timed = policy.predict_action_timed(_obs(3))
    assert timed.repaired_chunks == 3 and policy.repaired_chunks == 3 and policy.decoded_chunks == 3
    assert timed.model_calls == 1 and np.isfinite(timed.actions).all()
    # The repair is the kind's: all-zero coefficients, i.e. the middle of each dimension's range.
    np.testing.assert_allclose(timed.actions, np.zeros((3, H, A)), atol=1e-6)


def test_the_checkpoint_embeds_the_kind_and_predicts_the_same_without_its_folder(artifact, tmp_path):
    policy = _policy(artifact)
    policy.configure_inference(top_k=3)
    path = tmp_path / "policy.pt"
    policy.save(path)
    for file in artifact.directory.iterdir():  # the pipeline's folder is not needed to load
        file.rename(tmp_path / f"moved-{file.name}")
    try:
        loaded = load_policy(path)
    finally:
        for file in tmp_path.glob("moved-*"):
            file.rename(artifact.directory / file.name.removeprefix("moved-"))
    assert isinstance(loaded, NextTokenKindPolicy) and loaded.tokenizer_artifact.sha256 == artifact.sha256
    loaded.configure_inference(top_k=3)
    first = policy.predict_action(_obs(4), generator=torch.Generator().manual_seed(5))
    second = loaded.predict_action(_obs(4), generator=torch.Generator().manual_seed(5))
    np.testing.assert_array_equal(first, second)
    # Saved again, the copy keeps the embedded files byte for byte (and so their sha256).
    loaded.save(tmp_path / "again.pt")
    assert load_policy(tmp_path / "again.pt").tokenizer_artifact.sha256 == artifact.sha256


def test_a_checkpoint_whose_tokenizer_files_changed_is_refused(artifact, tmp_path):
    checkpoint = _policy(artifact).to_checkpoint()
    files = checkpoint["tokenizer_kind"]["files"]
    files["kind.json"] += b"\n"
    with pytest.raises(TokenizerMismatchError, match="recorded in the policy"):
        FAMILY.from_checkpoint(checkpoint)


def test_parameter_counts_are_reported_per_kind(artifact):
    policy = _policy(artifact)
    transformer = policy.transformer
    sequence = policy.sequence
    # What the kind changes: the embedding and the head (V' = V, plus the end token) and the position table.
    assert transformer.token_embedding.weight.numel() == sequence.output_size * TINY.width
    assert transformer.head.weight.numel() == sequence.output_size * TINY.width
    assert transformer.position_embedding.numel() == sequence.positions * TINY.width
    assert policy.num_parameters == sum(p.numel() for p in policy.parameters() if p.requires_grad)


def test_match_size_widens_the_network_to_its_size_over_carp_msvq(artifact, tmp_path):
    matched = dataclasses.replace(TINY, match_size=True)
    target = msvq_parameters(matched, OBS_DIM, OBS_STEPS, A, MSVQ)
    unmatched = _policy(artifact, scrambled=False)
    # The gap the setting closes: one vocabulary against A of them.
    assert count_parameters(unmatched.transformer) < 0.8 * target
    torch.manual_seed(0)
    policy = build(matched, _context(artifact, MSVQ))
    width = policy.transformer.config.width
    assert width % TINY.num_heads == 0 and width > TINY.width
    assert abs(count_parameters(policy.transformer) - target) <= 0.1 * target
    # No other multiple of num_heads comes nearer to the target.
    for other in (width - TINY.num_heads, width + TINY.num_heads):
        transformer = NextTokenKindPolicy.transformer_for(
            dataclasses.replace(TINY, width=other), OBS_DIM, OBS_STEPS, artifact.tokenizer
        )
        assert abs(count_parameters(transformer) - target) >= abs(count_parameters(policy.transformer) - target)
    # Sizing consumes no random draws: the weights are the ones an unmatched build at that width draws.
    torch.manual_seed(0)
    direct = build(dataclasses.replace(TINY, width=width), _context(artifact))
    for ours, theirs in zip(policy.transformer.parameters(), direct.transformer.parameters(), strict=True):
        assert torch.equal(ours, theirs)
    # The checkpoint records the chosen width and loads without the layout.
    policy.save(tmp_path / "policy.pt")
    loaded = load_policy(tmp_path / "policy.pt")
    assert loaded.transformer.config.width == width and loaded.num_parameters == policy.num_parameters


def test_match_size_needs_the_params_layout(artifact):
    with pytest.raises(ValueError, match="next_token.match_size needs the params' scales and codebook_size"):
        build(dataclasses.replace(TINY, match_size=True), _context(artifact))


def test_width_nearest_picks_the_nearest_multiple_of_the_heads_and_the_narrower_on_a_tie():
    def square(config: NextTokenConfig) -> torch.nn.Module:  # w * w + w trained parameters
        return torch.nn.Linear(config.width, config.width)

    config = NextTokenConfig(width=16, num_heads=2)
    assert width_nearest(config, 1000, square) == (dataclasses.replace(config, width=32), 1056)  # 930 at 30
    assert width_nearest(config, 993, square)[0].width == 30  # 930 and 1056 are 63 away: the narrower
    assert width_nearest(config, 1, square) == (dataclasses.replace(config, width=2), 6)
    assert width_nearest(config, 10**6, square)[0].width == 1000
    with pytest.raises(ValueError, match="must be >= 1"):
        width_nearest(config, 0, square)


def test_the_section_refuses_a_match_size_that_is_not_a_bool():
    with pytest.raises(ValueError, match="next_token.match_size=1: must be true or false"):
        NextTokenConfig(match_size=1)


class _FixedVocabulary:
    """Just the sizes a transformer is built from: V, the maximum token count and whether an end token closes a row."""

    def __init__(self, vocabulary_size: int, maximum: int, variable: bool) -> None:
        from carp.tokenizer.kinds.base import TokensPerChunk

        self.vocabulary_size, self.variable_length = vocabulary_size, variable
        self.tokens_per_chunk = TokensPerChunk.fixed(maximum)


def test_the_evaluation_summary_counts_the_repaired_chunks_of_the_policies_that_report_them():
    from carp.evaluation.rollout import EpisodeResult
    from carp.evaluation.runner import repair_summary

    reporting = [
        EpisodeResult(0, False, 8, 1.0, repaired_chunks=[0, 1]),
        EpisodeResult(1, True, 8, 1.0, repaired_chunks=[0, 0]),
    ]
    assert repair_summary(reporting) == {"repaired_chunks": 1, "predicted_chunks": 4, "repaired_chunk_rate": 0.25}
    assert repair_summary([EpisodeResult(0, False, 8, 1.0)]) == {}
