"""Batch-1 inference exported to ONNX and run by ONNX Runtime: the fast path of simulated evaluation.

Why a second execution path: at batch 1 the eager transformer spends most of its time per chunk dispatching hundreds
of tiny PyTorch operators (a (40 x 64) @ (64 x 192) matmul is a few microseconds of arithmetic and about as much
dispatch). ONNX Runtime runs the same computation as one static graph with a few microseconds per node
(`benchmarks/policy_speed.py` prints both).

Two graphs are exported, so that prediction and decoding stay separately timed:

- prediction: raw observations (1, To, Do) [and the task index (1,)] [and, for top-k sampling, the chunk's
  uniforms (1, L, k)] -> f_hat (1, A, C, l) and the chosen token sequence (1, L). Normalization, the observation
  encoder (a multi-task policy's task embedding), the condition, then
  K next-scale steps with a key/value cache that grows by concatenation (every scale's shapes are static), each
  step's tokens chosen (argmax, or the Gumbel-max draw of `carp.policies.carp.sampling.gumbel_top_k` from the
  uniforms the caller drew) and embedded by the tokenizer's quantizer.
- decoding: f_hat (1, A, C, l) -> raw actions (1, H, A): the tokenizer decoder and un-normalization.

The prediction graph restates :meth:`CoarseToFineTransformer.next_scale_logits` and the blocks' forward for batch
1, where the AdaLN shift and scale of a chunk are plain (D,) vectors and become the LayerNorm's own bias and weight
(one node instead of three), and attention is written out so that the exported graph has no shape arithmetic.
Folding the gates into the output projections as well is slower: ONNX Runtime pre-packs constant weights only.
Every learned piece (condition encoder, projections, head, tokenizer) is the policy's own module.
`tests/policies/carp/test_onnx_policy.py` checks that both paths choose the same tokens and return the same actions,
greedy and sampled (the same generator gives the same uniforms, hence the same draws).

`top_k` is fixed when the graphs are exported; batches run through `CarpPolicy`.
"""

from __future__ import annotations

import copy
import json
import math
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from carp.data.normalizer import MinMaxNormalizer
from carp.outputs import atomic_path
from carp.policies.base import TimedPrediction
from carp.policies.carp.blocks import MODULATIONS_PER_BLOCK, NORM_EPS
from carp.policies.carp.sampling import check_top_k, gumbel_top_k, sampling_uniforms
from carp.policies.carp.spec import POLICY_TYPE

if TYPE_CHECKING:
    from carp.policies.carp.policy import CarpPolicy

PREDICTION_FILE = "prediction.onnx"
DECODING_FILE = "decoding.onnx"
SUMMARY_FILE = "policy.json"
ONNX_OPSET = 18


def _normalizer_buffers(normalizer: MinMaxNormalizer, unnormalize: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Scale and offset (F,) float32 with `values * scale + offset` = the normalizer's (un)normalization."""
    features = normalizer.num_features
    zeros = np.zeros((1, features))
    offset = np.asarray(normalizer.unnormalize(zeros) if unnormalize else normalizer.normalize(zeros))
    scale = np.asarray(normalizer.unnormalize(zeros + 1) if unnormalize else normalizer.normalize(zeros + 1)) - offset
    return torch.as_tensor(scale[0], dtype=torch.float32), torch.as_tensor(offset[0], dtype=torch.float32)


class PredictionGraph(nn.Module):
    """Raw observations of one environment -> f_hat of the chosen chunk, in a form that exports to a static graph.

    Args:
        policy: trained policy; its transformer and a contiguous-memory copy of its tokenizer are used.
        top_k: 1 = greedy; k > 1 draws among the k best tokens with uniforms given as the last input.
    """

    def __init__(self, policy: CarpPolicy, top_k: int = 1) -> None:
        super().__init__()
        check_top_k(top_k, policy.spec.codebook_size)
        self.top_k = top_k
        self.multi_task = policy.num_tasks > 0
        self.observation_encoder = policy.observation_encoder
        self.transformer = policy.transformer
        # Channels-last kernels only matter to oneDNN; the exported graph is plain NCHW.
        self.tokenizer = copy.deepcopy(policy.tokenizer).to(memory_format=torch.contiguous_format)
        obs_scale, obs_offset = _normalizer_buffers(policy.obs_normalizer, unnormalize=False)
        self.register_buffer("obs_scale", obs_scale)
        self.register_buffer("obs_offset", obs_offset)
        # A multi-task policy's selected task may be narrower than its padded layout: the graph takes the task's own
        # observations and pads them with a 0/1 matrix (exact).
        padding = None if policy.tasks is None else policy.tasks.padding()
        if padding is not None and padding.pads:
            self.register_buffer("obs_padding", torch.as_tensor(padding.matrix()))  # (Do_task, Do)
        else:
            self.obs_padding = None

    def forward(self, obs: torch.Tensor, *extra: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict the chunk's f_hat.

        Args:
            obs: (1, To, Do) raw observations (a padded multi-task policy's selected task: its own Do_task).
            extra: the task index (1,) long for multi-task policies, then the uniforms (1, L, k) when top_k > 1.

        Returns:
            f_hat (1, A, C, l) accumulated over the K scales, and the chosen tokens (1, L) long in sequence order
            (docs/architecture.md, "Token layout and attention mask").
        """
        task_ids = extra[0] if self.multi_task else None
        uniforms = extra[-1] if self.top_k > 1 else None  # (1, L, k)
        transformer, quantizer = self.transformer, self.tokenizer.quantizer
        spec, layout = transformer.spec, transformer.layout
        width, heads, depth = spec.config.width, spec.config.num_heads, spec.config.depth
        head_width = width // heads
        if self.obs_padding is not None:
            obs = obs @ self.obs_padding  # (1, To, Do_task) -> (1, To, Do)
        features = self.observation_encoder(obs * self.obs_scale + self.obs_offset, None, task_ids)  # (1, To, F)
        condition = transformer.encode_condition(features)  # (1, D)
        # One Split of the flat vector: M (D,) outputs, where unbinding (1, M, 1, D) adds a Squeeze and a Reshape each.
        modulations = transformer.modulation_vector(condition).reshape(-1).split(width)  # M x (D,)
        positions = transformer.position_and_level()[0]  # (L, D)

        keys: list[torch.Tensor | None] = [None] * depth  # (1, Nh, n, D / Nh) of the scales so far
        values: list[torch.Tensor | None] = [None] * depth
        latent = self.tokenizer.empty_latent(1)  # (1, A, C, l)
        chosen = []
        attention_scale = 1.0 / math.sqrt(head_width)
        for scale_index, (start, end) in enumerate(layout.scale_bounds):
            tokens = end - start
            if scale_index == 0:
                hidden = condition + transformer.start_embedding[0]  # (s_1 * A, D)
            else:
                next_input = self.tokenizer.next_scale_input(latent, scale_index - 1)  # (1, A, C, s_k)
                hidden = transformer.token_projection(layout.scale_inputs_to_tokens(next_input)[0])  # (s_k * A, D)
            hidden = hidden + positions[start:end]
            for index, block in enumerate(transformer.blocks):
                offset = index * MODULATIONS_PER_BLOCK
                normed = F.layer_norm(hidden, (width,), modulations[offset + 1], modulations[offset], eps=NORM_EPS)
                qkv = block.attention.qkv(normed).view(tokens, 3, heads, head_width).permute(1, 2, 0, 3)
                query, key, value = qkv.split(1, dim=0)  # (1, Nh, s_k * A, D / Nh) each
                if keys[index] is not None:
                    key = torch.cat((keys[index], key), dim=2)  # (1, Nh, n, D / Nh)
                    value = torch.cat((values[index], value), dim=2)
                keys[index], values[index] = key, value
                weights = torch.softmax(torch.matmul(query, key.transpose(2, 3)) * attention_scale, dim=-1)
                attended = torch.matmul(weights, value).permute(2, 0, 1, 3).reshape(tokens, width)  # (s_k * A, D)
                hidden = block.attention.output(attended) * modulations[offset + 2] + hidden
                normed = F.layer_norm(hidden, (width,), modulations[offset + 4], modulations[offset + 3], eps=NORM_EPS)
                expanded = F.gelu(block.feed_forward.expand(normed))  # (s_k * A, hidden)
                hidden = block.feed_forward.contract(expanded) * modulations[offset + 5] + hidden
            normed = F.layer_norm(hidden, (width,), modulations[-1], modulations[-2], eps=NORM_EPS)
            logits = transformer.head(normed.unsqueeze(0))  # (1, s_k * A, V)
            if uniforms is None:
                scale_tokens = logits.argmax(dim=-1)  # (1, s_k * A)
            else:
                scale_tokens = gumbel_top_k(logits, uniforms[:, start:end])  # (1, s_k * A)
            chosen.append(scale_tokens)
            latent = latent + quantizer.scale_contribution(layout.scale_tokens_to_ids(scale_tokens), scale_index)
        return latent, torch.cat(chosen, dim=1)


class DecodingGraph(nn.Module):
    """f_hat (B, A, C, l) -> raw actions (B, H, A): the tokenizer decoder, then un-normalization."""

    def __init__(self, policy: CarpPolicy) -> None:
        super().__init__()
        self.tokenizer = copy.deepcopy(policy.tokenizer).to(memory_format=torch.contiguous_format)
        action_scale, action_offset = _normalizer_buffers(policy.action_normalizer, unnormalize=True)
        self.register_buffer("action_scale", action_scale)
        self.register_buffer("action_offset", action_offset)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        """Decode (B, A, C, l) into (B, H, A) raw actions."""
        return self.tokenizer.decode_latent(latent) * self.action_scale + self.action_offset


def _export(
    module: nn.Module, inputs: tuple[torch.Tensor, ...], names: list[str], outputs: list[str], path: Path
) -> None:
    """Trace `module` on `inputs` into the ONNX file `path` (written to a temporary name, then renamed).

    PyTorch's TorchScript-based exporter (`dynamo=False`) rather than its default `torch.export`-based one: both give
    graphs that choose the same tokens at the same ONNX Runtime latency, but tracing is many times quicker than
    `torch.export` with its decompositions, and the export runs once per evaluated task and sweep trial.
    Every shape here is static, so the tracer's warnings
    about Python values it records as constants (tensor sizes) do not apply, and its deprecation notice is not
    actionable while torch is pinned.
    """
    with atomic_path(path) as temporary, torch.no_grad(), warnings.catch_warnings():
        # One eager call first fills the tokenizer's cached resampling matrices, which the trace then records as
        # constants.
        module.eval()(*inputs)
        for category in (torch.jit.TracerWarning, DeprecationWarning, FutureWarning):
            warnings.simplefilter("ignore", category)
        torch.onnx.export(
            module,
            inputs,
            str(temporary),
            dynamo=False,
            opset_version=ONNX_OPSET,
            input_names=names,
            output_names=outputs,
            verbose=False,
        )


def export_policy_graphs(policy: CarpPolicy, directory: Path, top_k: int = 1) -> Path:
    """Write the prediction and decoding graphs of a CPU policy into `directory` (created); returns `directory`.

    Runs once per evaluation.

    Args:
        policy: the trained policy.
        directory: destination of the two graphs.
        top_k: token choice baked into the prediction graph (1 = greedy; k > 1 = top-k draws from given uniforms).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    policy = policy.to("cpu").eval()
    spec = policy.spec
    prediction = PredictionGraph(policy, top_k)
    padding = None if policy.tasks is None else policy.tasks.padding()
    obs_dim = policy.obs_normalizer.num_features if padding is None else padding.input_dim
    inputs, names = [torch.zeros(1, spec.obs_steps, obs_dim)], ["obs"]
    if policy.num_tasks > 0:
        inputs.append(torch.zeros(1, dtype=torch.long))
        names.append("task_ids")
    if top_k > 1:
        inputs.append(torch.full((1, spec.sequence_length, top_k), 0.5))
        names.append("uniforms")
    _export(prediction, tuple(inputs), names, ["latent", "tokens"], directory / PREDICTION_FILE)
    latent = policy.tokenizer.empty_latent(1)
    _export(DecodingGraph(policy), (latent,), ["latent"], ["actions"], directory / DECODING_FILE)
    # What the graphs cannot tell: the report's per-row facts about the policy they came from.
    summary = {
        "model_calls_per_chunk": policy.model_calls_per_chunk,
        "num_parameters": policy.num_parameters,
        "metadata": policy.metadata,
        # A multi-task policy's graphs bake in its selected task's statistics; that task is the default task index.
        "task_index": None if policy.tasks is None else policy.tasks.index(policy.tasks.selected),
    }
    (directory / SUMMARY_FILE).write_text(json.dumps(summary))
    return directory


class OnnxPolicy:
    """Runs the graphs of :func:`export_policy_graphs` on one CPU thread, one environment at a time.

    A :class:`~carp.policies.base.Policy` for prediction (it cannot be trained or saved).

    Args:
        directory: where :func:`export_policy_graphs` wrote the graphs.
        threads: ONNX Runtime intra-op threads (1: the simulator uses the other core).
    """

    def __init__(self, directory: Path, threads: int = 1) -> None:
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3  # errors only
        directory = Path(directory)
        self._prediction = onnxruntime.InferenceSession(
            str(directory / PREDICTION_FILE), options, providers=["CPUExecutionProvider"]
        )
        self._decoding = onnxruntime.InferenceSession(
            str(directory / DECODING_FILE), options, providers=["CPUExecutionProvider"]
        )
        inputs = {item.name: item for item in self._prediction.get_inputs()}
        self._takes_task = "task_ids" in inputs
        # Greedy graphs take no uniforms; sampling graphs take (1, L, k).
        self._uniforms_shape = tuple(inputs["uniforms"].shape) if "uniforms" in inputs else None
        summary = json.loads((directory / SUMMARY_FILE).read_text())
        self._model_calls = int(summary["model_calls_per_chunk"])
        self._num_parameters = int(summary["num_parameters"])
        self.metadata = summary["metadata"]
        self._default_task = summary.get("task_index")
        self._directory = directory

    policy_type = POLICY_TYPE

    def configure_inference(self, top_k: int = 1) -> None:
        """Check that the graphs were exported with this token choice (it is baked into them)."""
        if top_k != self.top_k:
            raise ValueError(f"the ONNX graphs in {self._directory} use top_k = {self.top_k}, got top_k = {top_k}")

    @property
    def model_calls_per_chunk(self) -> int:
        """`K`, the scales the prediction graph steps through."""
        return self._model_calls

    @property
    def num_parameters(self) -> int:
        """Parameters of the exported transformer."""
        return self._num_parameters

    @property
    def description(self) -> str:
        """`greedy` or `top-<k>`."""
        return "greedy" if self.top_k == 1 else f"top-{self.top_k}"

    @property
    def draws_random(self) -> bool:
        """A graph exported with top_k > 1 takes drawn uniforms."""
        return self.top_k > 1

    @property
    def top_k(self) -> int:
        """The token choice the graph was exported with (1 = greedy)."""
        return 1 if self._uniforms_shape is None else self._uniforms_shape[-1]

    def predict_action_timed(
        self, obs: np.ndarray, task_index: int | None = None, generator: torch.Generator | None = None
    ) -> TimedPrediction:
        """Raw observations (1, To, Do) -> raw actions (1, H, A) float32 and the two durations in seconds.

        `generator` (CPU) supplies the top-k draws of a sampling graph, as it would to `CarpPolicy`.
        """
        return self._predict(obs, task_index, generator)[0]

    def predict_action(
        self, obs: np.ndarray, task_index: int | None = None, generator: torch.Generator | None = None
    ) -> np.ndarray:
        """Raw actions (1, H, A) float32 of raw observations (1, To, Do)."""
        return self._predict(obs, task_index, generator)[0].actions

    def predict_tokens(
        self, obs: np.ndarray, task_index: int | None = None, generator: torch.Generator | None = None
    ) -> np.ndarray:
        """The token sequence (1, L) int64 chosen for raw observations (1, To, Do)."""
        return self._predict(obs, task_index, generator)[1]

    def _predict(
        self, obs: np.ndarray, task_index: int | None, generator: torch.Generator | None
    ) -> tuple[TimedPrediction, np.ndarray]:
        obs = np.asarray(obs, dtype=np.float32)
        expected = tuple(self._prediction.get_inputs()[0].shape)
        if obs.shape != expected:
            raise ValueError(f"obs must have shape {expected} (one environment), got {obs.shape}")
        if self._takes_task and task_index is None:
            task_index = self._default_task
        if self._takes_task != (task_index is not None):
            needed = "needs a task index" if self._takes_task else "is single-task but a task index was given"
            raise ValueError(f"this policy {needed}")
        feeds = {"obs": obs}
        if self._takes_task:
            feeds["task_ids"] = np.asarray([task_index], dtype=np.int64)
        started = time.perf_counter()
        if self._uniforms_shape is not None:
            feeds["uniforms"] = sampling_uniforms(*self._uniforms_shape, generator=generator).numpy()
        latent, tokens = self._prediction.run(None, feeds)
        predicted = time.perf_counter()
        (actions,) = self._decoding.run(None, {"latent": latent})
        decoded = time.perf_counter()
        return TimedPrediction(actions, predicted - started, decoded - predicted, self._model_calls), tokens
