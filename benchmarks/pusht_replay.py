"""Replay a Push-T LeRobotDataset's episodes in carp's Push-T and compare the reward reached with the recorded one.

Each episode starts from its first frame's state (for ``lerobot/pusht_keypoints``: the agent position and the block
pose fitted to the T's vertices, `carp.tasks.pusht.lerobot`) and runs its recorded actions open loop. A row gives the
highest recorded ``next.reward``, the highest reward of the replay, the largest gap between the two after the same
step, and whether the replay reached the recorded reward. Human demonstrations carry no seed, so this replays from
the recorded state rather than a seeded reset; the exit status is 1 when an episode falls short.

    .venv/bin/python benchmarks/pusht_replay.py datasets/pusht_keypoints [--episodes 20]
"""

import argparse
import sys
from pathlib import Path

from carp.data.lerobot.reader import read_lerobot_demonstrations
from carp.data.robomimic_schema import DatasetError
from carp.tasks.pusht import env as pusht_env
from carp.tasks.pusht.lerobot import REPLAY_TOLERANCE, PushTKeypoints, check_replays


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path, help="a LeRobotDataset folder in lerobot/pusht_keypoints' layout")
    parser.add_argument("--episodes", type=int, default=None, help="the first this many episodes (default: all)")
    arguments = parser.parse_args()
    if arguments.episodes is not None and arguments.episodes < 1:
        sys.exit(f"error: --episodes {arguments.episodes}: expected at least 1")
    try:
        # Read as the collect stage reads it for Push-T: DP's keys, derived from the T's vertices where absent.
        demos = read_lerobot_demonstrations(
            arguments.dataset, tuple(pusht_env.OBSERVATION_DIMS), action_dim=pusht_env.ACTION_DIM,
            env_name=pusht_env.ENV_NAME, env_args=pusht_env.make_env_args(), adapter=PushTKeypoints(),
        )  # fmt: skip
        checks = check_replays(demos, arguments.episodes)
    except DatasetError as error:
        sys.exit(f"error: {error}")
    print(f"{'episode':<14}{'steps':>6}{'recorded':>10}{'replayed':>10}{'largest gap':>13}  reached")
    for check in checks:
        print(
            f"{check.episode:<14}{check.steps:>6}{check.recorded_reward:>10.4f}{check.replayed_reward:>10.4f}"
            f"{check.largest_gap:>13.2e}  {'yes' if check.reached else 'no'}"
        )
    reached = sum(check.reached for check in checks)
    print(f"{reached}/{len(checks)} episodes reach their recorded reward (within {REPLAY_TOLERANCE:g})")
    if reached < len(checks):
        sys.exit(1)


if __name__ == "__main__":
    main()
