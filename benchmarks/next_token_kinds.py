"""Trained parameters of the next-token policy over every tokenizer kind, and the width that matches carp_msvq's.

The kind changes the embedding and the head (V ids, plus an end token for FAST; carp_msvq: one V-row vocabulary per
action dimension) and the position table (L, or FAST's fitted maximum + 1); the blocks are the `next_token`
section's. Each kind is built from params.yaml's `tokenizer_<kind>` section; FAST, whose vocabulary and maximum
length come from fitting, is fitted on the training windows of the task's ingested demos
(``data/processed/<task>/``). For each kind the table gives its count at the section's width, the ratio to
carp_msvq's, and the width (a multiple of `num_heads`) whose count is closest to carp_msvq's, with that count: the
width `next_token.match_size` (the default) trains each kind at.

    .venv/bin/python benchmarks/next_token_kinds.py [--task lift] [--params params.yaml]
"""

import argparse
from pathlib import Path

import torch

from carp.config import load_params
from carp.config.tokenizer_kinds import kind_section
from carp.data.dataset import load_task_windows
from carp.policies.base import count_parameters
from carp.policies.carp.layout import TokenLayout
from carp.policies.context import MsvqLayout
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.kind_policy import NextTokenKindPolicy
from carp.policies.next_token.matched_size import msvq_parameters, width_nearest
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.tokenizer.kinds.registry import build_tokenizer, kind_names


def kind_transformer(config: NextTokenConfig, obs_dim: int, obs_steps: int, tokenizer) -> NextTokenTransformer:
    return NextTokenKindPolicy.transformer_for(config, obs_dim, obs_steps, tokenizer)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="lift")
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    arguments = parser.parse_args()
    params = load_params(arguments.params)
    config = params.family_config("next_token")
    data = params.data
    windows = load_task_windows(
        Path("data/processed") / arguments.task, data.action_horizon, data.obs_steps, data.action_steps
    )
    obs_dim, action_dim = windows.train_obs.shape[-1], windows.train_actions.shape[-1]
    train = torch.as_tensor(windows.action_normalizer.normalize(windows.train_actions), dtype=torch.float32)
    torch.manual_seed(0)
    layout = MsvqLayout(tuple(params.scales), params.codebook_size)
    target = msvq_parameters(config, obs_dim, data.obs_steps, action_dim, layout)
    positions = TokenLayout(action_dim, layout.scales).sequence_length
    rows = [("carp_msvq", params.codebook_size, positions, target, config.width, target)]
    for kind in kind_names()[1:]:
        tokenizer = build_tokenizer(kind, getattr(params, kind_section(kind)), action_dim, data.action_horizon)
        if kind == "fast":
            tokenizer.fit(train)
        transformer = kind_transformer(config, obs_dim, data.obs_steps, tokenizer)

        def build(changed: NextTokenConfig, tokenizer=tokenizer) -> NextTokenTransformer:
            return kind_transformer(changed, obs_dim, data.obs_steps, tokenizer)

        matched_config, matched = width_nearest(config, target, build)
        rows.append(
            (
                kind,
                transformer.codebook_size,
                transformer.sequence_length,
                count_parameters(transformer),
                matched_config.width,
                matched,
            )
        )
    print(f"next_token at depth {config.depth}, width {config.width}; {arguments.task}: A={action_dim}, Do={obs_dim}")
    print("| kind | output ids | positions | parameters | vs carp_msvq | matching width | parameters there |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for kind, ids, positions, parameters, width, matched in rows:
        print(
            f"| {kind} | {ids} | {positions} | {parameters:,} | {parameters / target:.2f} | {width} | "
            f"{matched:,} ({matched / target:.2f}) |"
        )


if __name__ == "__main__":
    main()
