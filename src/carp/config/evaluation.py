"""The `eval` section: test and validation episodes, checkpoint selection and the rollouts' backend."""

from dataclasses import dataclass, field

from carp.config.checks import EVAL_BACKENDS, SELECTION_RULES, _require, require_bool, require_positive_int


@dataclass(frozen=True)
class EvalConfig:
    """Simulated evaluation (docs/architecture.md, "Evaluation protocol").

    Attributes:
        episodes: Seeded evaluation episodes per task; an integer >= 1. The success rate is reported with its 95%
            Wilson interval, which narrows with more episodes.
        seed: First evaluation seed; an integer >= 0. Episode i uses ``seed + i``. The range ``[seed, seed +
            episodes)`` must not overlap the collection seeds ``[data.collection_seed, data.collection_seed + 3 *
            demos)``, with demos the largest per-task demo count.
        workers: Simulator worker processes, each with its own copy of the policy; an integer >= 0, where 0 means
            one per CPU core.
        max_steps: Task -> step limit of one episode, in the task's control steps (20 Hz for the arms, 10 Hz for
            Push-T); each an integer >= 1. A task without an entry gets its protocol's limit (arms 400, Push-T 300);
            an episode that has not succeeded by then counts as a failure.
        video: Record GIF videos of the first ``video_episodes`` episodes of each task and policy, from the agent-view
            camera, into ``reports/eval/videos/``, which the report shows (needs offscreen rendering through EGL);
            true or false.
        video_episodes: Episodes recorded per task when ``video`` is true; an integer >= 0.
        backend: ``onnxruntime`` runs batch-1 inference as exported ONNX graphs, several times faster per chunk than
            the eager modules (see ``carp.policies.carp.onnx_policy``); ``torch`` runs the PyTorch modules. Both choose
            the same tokens.
        selection: Which of a training run's candidate policies (its snapshots, ``training.snapshot_every`` and
            ``snapshot_last``, and the final policy) is evaluated on the test seeds: ``final``, ``best_validation``
            (the highest success on the validation seeds; ties go to the later epoch), ``lowest_loss`` (the lowest
            training loss of its epoch) or ``average_last`` (one policy whose weights are the mean of the last
            ``average_last`` candidates', by epoch). The choice is fixed before any test episode runs.
        validation_episodes: Episodes per candidate policy on the validation seeds; an integer >= 0, at least 1 with
            ``selection: best_validation``. With 0 no validation episode runs.
        validation_seed: First validation seed; an integer >= 0. Validation episode i uses ``validation_seed + i``;
            the range must not overlap the test seeds ``[seed, seed + episodes)`` nor the collection seeds.
        validation_top_k: The report's Diffusion-Policy-style figure: the mean validation success of the this many best
            candidates, next to their maximum and the confirmed test success; an integer >= 1.
        average_last: With ``selection: average_last``, how many of the latest candidates are averaged; an integer
            >= 1 (1 is the final policy), at most the candidates the training keeps (checked when evaluating).
        ensemble_m: How a policy's chunks are executed: ``null`` (the default, carp's protocol and the CARP paper's)
            runs ``data.action_steps`` actions of each chunk, then predicts the next; a number >= 0 predicts a chunk at
            every control step and executes the temporal ensemble of the overlapping chunks (ACT's weights
            ``exp(-m * i)``, i = 0 the oldest prediction; 0 = their plain mean, VQ-BeT's Push-T inference), every
            family alike. Costs ``Ta`` times the predictions per episode.
        run_test: Whether the selected candidate runs on the test seeds; true or false. False runs the validation
            episodes only and writes a summary of the selected candidate's validation figures (``validation_score``,
            ``validation_success_rate``) with no test figure, no test episode and nothing for the report stage to
            compare; it needs ``validation_episodes >= 1`` and a rule that selects one candidate (not
            ``average_last``). The sweep sets it false for its trials, so that choosing settings never touches the
            test seeds; leave it true in the pipeline.
    """

    episodes: int = 50
    seed: int = 100_000
    workers: int = 0
    max_steps: dict[str, int] = field(default_factory=lambda: {"lift": 400, "can": 400, "square": 400})
    video: bool = False
    video_episodes: int = 2
    backend: str = "onnxruntime"
    selection: str = "final"
    validation_episodes: int = 0
    validation_seed: int = 200_000
    validation_top_k: int = 3
    average_last: int = 3
    ensemble_m: float | None = None
    run_test: bool = True

    def validation_seeds(self) -> list[int]:
        """The seeds of the validation episodes, which select a checkpoint."""
        return [self.validation_seed + index for index in range(self.validation_episodes)]

    def test_seeds(self) -> list[int]:
        """The seeds of the test episodes, which confirm the selected checkpoint."""
        return [self.seed + index for index in range(self.episodes)]

    def __post_init__(self) -> None:
        _require(self.episodes >= 1, "eval.episodes", self.episodes, "must be >= 1")
        _require(self.seed >= 0, "eval.seed", self.seed, "must be >= 0")
        _require(self.workers >= 0, "eval.workers", self.workers, "must be >= 0 (0 = one per core)")
        for task, steps in self.max_steps.items():
            _require(steps >= 1, f"eval.max_steps.{task}", steps, "must be >= 1")
        _require(self.video_episodes >= 0, "eval.video_episodes", self.video_episodes, "must be >= 0")
        _require(self.backend in EVAL_BACKENDS, "eval.backend", self.backend, f"must be one of {EVAL_BACKENDS}")
        _require(
            self.selection in SELECTION_RULES, "eval.selection", self.selection, f"must be one of {SELECTION_RULES}"
        )
        _require(self.validation_episodes >= 0, "eval.validation_episodes", self.validation_episodes, "must be >= 0")
        _require(
            self.selection != "best_validation" or self.validation_episodes >= 1,
            "eval.validation_episodes",
            self.validation_episodes,
            "must be >= 1 with selection: best_validation",
        )
        _require(self.validation_seed >= 0, "eval.validation_seed", self.validation_seed, "must be >= 0")
        _require(self.validation_top_k >= 1, "eval.validation_top_k", self.validation_top_k, "must be >= 1")
        require_positive_int("eval.average_last", self.average_last)
        _require(
            self.ensemble_m is None or (not isinstance(self.ensemble_m, bool) and self.ensemble_m >= 0),
            "eval.ensemble_m",
            self.ensemble_m,
            "must be null or a number >= 0",
        )
        require_bool("eval.run_test", self.run_test)
        _require(
            self.run_test or self.validation_episodes >= 1,
            "eval.run_test",
            self.run_test,
            "false needs validation episodes: set eval.validation_episodes >= 1",
        )
        _require(
            self.run_test or self.selection != "average_last",
            "eval.run_test",
            self.run_test,
            "false needs a rule that selects one validated candidate, not average_last",
        )
        validation_end = self.validation_seed + self.validation_episodes
        _require(
            self.validation_episodes == 0
            or validation_end <= self.seed
            or self.validation_seed >= self.seed + self.episodes,
            "eval.validation_seed",
            self.validation_seed,
            f"validation seeds [{self.validation_seed}, {validation_end}) overlap the test seeds "
            f"[{self.seed}, {self.seed + self.episodes})",
        )
