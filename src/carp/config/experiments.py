"""The sections around runs: `study`, `comparison`, `tracking` and `sweep`."""

from dataclasses import dataclass

from carp.config.checks import SWEEP_PRUNERS, _distinct_paths, _require, require_registry_alias
from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND, TOKENIZER_KINDS


@dataclass(frozen=True)
class StudyConfig:
    """The paper's studies, each run as DVC experiments by ``make study STUDY=<name>`` (outside the default DAG).

    Attributes:
        data_efficiency_sizes: Demo counts of the data-efficiency study (supplementary Fig. 5): one experiment per
            size with ``data.subset_size`` set to it and ``data.num_demos`` to the largest, so that every size draws
            from one collected file and the subsets are nested; at least two, strictly increasing integers >= 1.
        scale_schedules: Points of the scales study (supplementary Fig. 10): one experiment per schedule with
            ``scales`` set to it, each compared with the workspace's own ``scales``, which must be one of them; at
            least two schedules, each as ``scales`` requires, no two of the same length K.
        codebook_sizes: Points of the codebook study: one experiment per size with ``codebook_size`` set to it, each
            compared with the workspace's own ``codebook_size``, which must be one of them; at least two strictly
            increasing integers >= 2.
        references: Folders of other runs of the same study (their ``reports/studies/<study>``, or a copy kept with
            the project) whose families the study's report adds to its own at every point, so that a study split
            over clones or machines (one family or training seed each) is reported as one. For the data-efficiency
            study each must hold a finished ``size<N>/`` for every size and the subsets must be the same
            (``data.num_demos``, ``data.subset_seed`` and the collection alike); the scales and codebook studies take
            whichever points a folder holds. A training seed of a family on a task may come from one place only.
            Paths relative to the project root, each at most once. Empty (the default): the study's own experiments
            only.
        replay_demos: Demos of each task replayed open loop through each point's tokenizer by the scales and codebook
            studies (the first this many of the task's demo file), so the report shows what each point's rate costs
            in task success before any policy is trained; an integer >= 0, 0 replays none. The tokenizer studies
            replay the same way.
        tokenizer_kinds: Points of the tokenizer study: one experiment per kind with ``tokenizer.kind`` set to it
            (each at the rate its ``tokenizer_<kind>`` section sets), every family of ``policies`` that takes the kind
            trained there and compared with the same family at carp_msvq; at least two distinct kinds of
            ``tokenizer.kind``'s, carp_msvq among them.
        reuse_source_tasks: Tasks whose demos train the tokenizer that the reuse study registers and reuses; at
            least one, distinct, none of ``reuse_target_tasks``.
        reuse_target_tasks: Tasks the reuse study trains and evaluates twice, with their own tokenizer and with the
            source tasks' registered one; at least one, distinct, each scored in the simulator.
    """

    data_efficiency_sizes: tuple[int, ...] = (30, 60, 100, 200)
    scale_schedules: tuple[tuple[int, ...], ...] = (
        (1,),
        (1, 2),
        (1, 2, 3),
        (1, 2, 3, 4),
        (1, 2, 3, 4, 5),
        (1, 2, 3, 4, 5, 6),
    )
    codebook_sizes: tuple[int, ...] = (64, 256, 512, 1024)
    references: tuple[str, ...] = ()
    replay_demos: int = 50
    tokenizer_kinds: tuple[str, ...] = TOKENIZER_KINDS
    reuse_source_tasks: tuple[str, ...] = ("lift", "can", "square", "stack")
    reuse_target_tasks: tuple[str, ...] = ("nut_assembly", "threading", "stack_three")

    def __post_init__(self) -> None:
        _require(self.replay_demos >= 0, "study.replay_demos", self.replay_demos, "must be >= 0 (0 replays none)")
        sizes = list(self.data_efficiency_sizes)
        _require(
            len(sizes) >= 2 and sizes[0] >= 1 and all(a < b for a, b in zip(sizes, sizes[1:])),
            "study.data_efficiency_sizes",
            sizes,
            "must hold at least two strictly increasing sizes >= 1",
        )
        object.__setattr__(self, "scale_schedules", tuple(tuple(schedule) for schedule in self.scale_schedules))
        lengths = [len(schedule) for schedule in self.scale_schedules]
        _require(
            len(lengths) >= 2 and len(set(lengths)) == len(lengths),
            "study.scale_schedules",
            [list(schedule) for schedule in self.scale_schedules],
            "must hold at least two schedules, no two with the same number of scales",
        )
        codebooks = list(self.codebook_sizes)
        _require(
            len(codebooks) >= 2 and codebooks[0] >= 2 and all(a < b for a, b in zip(codebooks, codebooks[1:])),
            "study.codebook_sizes",
            codebooks,
            "must hold at least two strictly increasing sizes >= 2",
        )
        object.__setattr__(self, "references", _distinct_paths("study.references", self.references))
        kinds = list(self.tokenizer_kinds)
        _require(
            len(kinds) >= 2 and len(set(kinds)) == len(kinds) and DEFAULT_TOKENIZER_KIND in kinds,
            "study.tokenizer_kinds",
            kinds,
            f"must hold at least two distinct kinds, {DEFAULT_TOKENIZER_KIND} (the reference) among them",
        )
        for kind in kinds:
            _require(
                kind in TOKENIZER_KINDS, "study.tokenizer_kinds", kinds, f"every kind must be one of {TOKENIZER_KINDS}"
            )
        for key in ("reuse_source_tasks", "reuse_target_tasks"):
            tasks = list(getattr(self, key))
            _require(
                len(tasks) >= 1 and len(set(tasks)) == len(tasks),
                f"study.{key}",
                tasks,
                "must hold at least one task, each once",
            )
            object.__setattr__(self, key, tuple(tasks))
        shared = sorted(set(self.reuse_source_tasks) & set(self.reuse_target_tasks))
        _require(
            not shared,
            "study.reuse_target_tasks",
            list(self.reuse_target_tasks),
            f"must not hold a source task ({', '.join(shared)}): the reused tokenizer is to be new to them",
        )


@dataclass(frozen=True)
class ComparisonConfig:
    """How the report compares policy families on a task (read by the report stage only).

    Attributes:
        margin: Equivalence margin in success rate (0.05 = 5 percentage points): two families are "on par" when the
            (1 - 2 alpha) interval over training seeds of their difference lies inside (-margin, margin); a number
            in (0, 1).
        alpha: Family-wise significance level of all the verdicts a report (or a study's report) states: every
            pair's test of a difference and its test of equivalence go into one step-down correction; a number in
            (0, 0.5).
        min_seeds: Training seeds per family that a family verdict needs (the training seed is the unit of a family
            claim); a pair with fewer gets "not decided (n training seeds)" and its figures describe the trained
            networks only; an integer >= 2.
        references: Evaluation directories of other runs (their ``reports/eval``, or a copy of it kept with the
            project) whose evaluations of this run's tasks the report adds to its own: more training seeds of a
            family, families trained elsewhere, the single-task policies beside a multi-task one. Paths relative to
            the project root, each at most once; a training seed of a family on a task may come from one place only.
            The episodes pair by episode seed, so reference runs evaluated on the same test seeds. The report stage
            reruns when this list changes (``dvc repro -f report`` after a referenced directory changes). Empty (the
            default): the run's own evaluations only.
    """

    margin: float = 0.05
    alpha: float = 0.05
    min_seeds: int = 3
    references: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _require(0 < self.margin < 1, "comparison.margin", self.margin, "must lie in (0, 1)")
        _require(0 < self.alpha < 0.5, "comparison.alpha", self.alpha, "must lie in (0, 0.5)")
        _require(
            isinstance(self.min_seeds, int) and not isinstance(self.min_seeds, bool) and self.min_seeds >= 2,
            "comparison.min_seeds",
            self.min_seeds,
            "must be an integer >= 2 (one training seed says nothing about a family)",
        )
        object.__setattr__(self, "references", _distinct_paths("comparison.references", self.references))


@dataclass(frozen=True)
class TrackingConfig:
    """MLflow tracking (runs, metrics, artifacts and the model registry).

    Attributes:
        uri: MLflow tracking URI; not empty. A relative SQLite path (``sqlite:///mlflow.db``) is resolved against the
            project root, also for experiments run in a temporary copy.
        experiment_prefix: Prefix of the MLflow experiment names: ``<prefix>-<task>``, ``<prefix>-tokenizer`` and
            ``<prefix>-sweep``; not empty.
        policy_alias: Alias the ``register_policy`` stage points at the policies it registers (families in
            ``register``): ``<alias>-seed<k>`` at training seed k's version of ``carp-policy-<task>-<family>``, and
            ``<alias>`` itself at the version of the first seed in ``seeds``. Letters, digits, ``_`` and ``-``, not
            ``latest``, not ``v<digits>`` and not starting with a digit (reserved by the MLflow registry).
    """

    uri: str = "sqlite:///mlflow.db"
    experiment_prefix: str = "carp"
    policy_alias: str = "candidate"

    def __post_init__(self) -> None:
        _require(bool(self.uri), "tracking.uri", self.uri, "must be set")
        _require(bool(self.experiment_prefix), "tracking.experiment_prefix", self.experiment_prefix, "must be set")
        require_registry_alias("tracking.policy_alias", self.policy_alias)


@dataclass(frozen=True)
class SweepConfig:
    """Optuna study over scale schedules and codebook sizes (``make sweep``; outside the default DAG).

    Attributes:
        study_name: Name of the Optuna study, also part of each trial's DVC experiment name
            (``sweep-<study>-t<number>``); a changed search space needs a new name.
        storage: Optuna storage URL; a relative SQLite path (``sqlite:///optuna.db``) is resolved against the project
            root. Sweep workers in several workspaces (or on several machines) share one study through a PostgreSQL
            URL such as ``postgresql://mlflow@127.0.0.1:5432/optuna`` (password from ``~/.pgpass`` or ``PGPASSFILE``).
        num_trials: Total number of finished trials (complete, pruned or failed), counted across restarts of the
            sweep and across the workers sharing its study; an integer >= 1.
        scale_schedules: Candidate values of ``scales``; at least one, each as ``scales`` requires.
        codebook_sizes: Candidate values of ``codebook_size``; each an integer >= 2.
        prune_factor: A trial whose tokenizer reconstruction error is more than this many times the lowest error of
            the study so far is pruned before its policy is trained; a number > 1.
        heartbeat_seconds: How often a running trial marks itself alive in the storage, in seconds; an integer >= 1.
            A killed sweep's trial is retried once its heartbeat is two intervals old.
        git_remote: Git remote (a name such as ``origin``, or a URL) that every completed trial's DVC experiment is
            pushed to (``dvc exp push``, which also pushes its outputs to the default DVC remote when there is one),
            so that the experiments of every worker can be pulled into any workspace; empty: nothing is pushed.
        pruner: How Optuna stops a trial early from its snapshots' validation scores, which the trial reports as the
            evaluate stage produces them (see ``carp.sweep.pruning``): ``successive_halving``, ``hyperband`` or
            ``none``. The tokenizer check (``prune_factor``) applies whatever the choice.
        validation_episodes: Episodes per candidate policy on the validation seeds (from ``eval.validation_seed``)
            in every trial and in the confirmation, which select on them; the sweep sets it as their
            ``eval.validation_episodes``, whatever the ``eval`` section says. An integer >= 1; a few dozen tell trials
            apart.
        confirm_seeds: Training seeds of the confirmation that ends the sweep: the selected trial's settings and the
            default ones (``scales`` and ``codebook_size`` of the committed params file) are each trained once per
            seed and evaluated on the test seeds, and their paired comparison is the sweep's result; distinct integers
            >= 0, at least two and at least ``comparison.min_seeds`` (fewer could never confirm anything), and none
            of ``seeds`` (the sweep checks it): the winner's trial networks were chosen for their validation score,
            and a confirmation that reused one would measure the selected settings with that luck included.
    """

    study_name: str = "carp-sweep"
    storage: str = "sqlite:///optuna.db"
    num_trials: int = 8
    scale_schedules: tuple[tuple[int, ...], ...] = ((4,), (1, 4), (1, 2, 4), (1, 2, 3, 4))
    codebook_sizes: tuple[int, ...] = (64, 256, 512)
    prune_factor: float = 2.0
    heartbeat_seconds: int = 10
    git_remote: str = ""
    pruner: str = "successive_halving"
    validation_episodes: int = 20
    confirm_seeds: tuple[int, ...] = (1, 2, 3)

    def __post_init__(self) -> None:
        _require(self.num_trials >= 1, "sweep.num_trials", self.num_trials, "must be >= 1")
        _require(len(self.scale_schedules) >= 1, "sweep.scale_schedules", self.scale_schedules, "must not be empty")
        for size in self.codebook_sizes:
            _require(size >= 2, "sweep.codebook_sizes", self.codebook_sizes, "every size must be >= 2")
        _require(self.prune_factor > 1.0, "sweep.prune_factor", self.prune_factor, "must be > 1")
        _require(self.heartbeat_seconds >= 1, "sweep.heartbeat_seconds", self.heartbeat_seconds, "must be >= 1")
        _require(
            self.git_remote == self.git_remote.strip() and not self.git_remote.startswith("-"),
            "sweep.git_remote",
            self.git_remote,
            "must be a git remote name or URL, without surrounding spaces or a leading '-'",
        )
        _require(self.pruner in SWEEP_PRUNERS, "sweep.pruner", self.pruner, f"must be one of {SWEEP_PRUNERS}")
        _require(self.validation_episodes >= 1, "sweep.validation_episodes", self.validation_episodes, "must be >= 1")
        seeds = list(self.confirm_seeds)
        _require(
            len(seeds) >= 2
            and all(isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0 for seed in seeds)
            and len(set(seeds)) == len(seeds),
            "sweep.confirm_seeds",
            seeds,
            "must hold at least two distinct integer seeds >= 0",
        )
