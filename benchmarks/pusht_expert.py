"""The scripted Push-T expert's success rate and speed over a range of DP test seeds.

Each episode resets Push-T to DP's initial state for its seed (``carp.tasks.pusht.env.reset_state``) and lets a fresh
``PushTExpert`` act until success or the 300-step limit. The table reports the successes, the wall time per episode
(planning and simulation together, on whatever load the machine has) and the control steps per episode.

Usage: python benchmarks/pusht_expert.py [--episodes 50] [--first-seed 1000] [--expert-seed 0]
"""

import argparse
import time

import numpy as np
from tqdm import tqdm

from carp.tasks.pusht.env import PushTEnv
from carp.tasks.pusht.expert import push_library, run_episode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument(
        "--first-seed", type=int, default=1000, help="episodes use seeds first-seed, first-seed + 1, ..."
    )
    parser.add_argument("--expert-seed", type=int, default=0, help="the expert's tie-breaking seed")
    arguments = parser.parse_args()

    started = time.perf_counter()
    push_library()  # built once per process, so it is timed apart from the episodes
    library_seconds = time.perf_counter() - started

    env = PushTEnv(render_size=96)
    successes, seconds, steps, failed_seeds = 0, [], [], []
    seeds = range(arguments.first_seed, arguments.first_seed + arguments.episodes)
    for seed in tqdm(seeds, desc="episodes"):
        started = time.perf_counter()
        success, episode_steps = run_episode(env, seed, expert_seed=arguments.expert_seed)
        seconds.append(time.perf_counter() - started)
        steps.append(episode_steps)
        successes += success
        if not success:
            failed_seeds.append(seed)
    env.close()

    print(f"seeds {seeds.start}..{seeds.stop - 1}, expert seed {arguments.expert_seed}")
    print(f"{'successes':<24}{successes} / {arguments.episodes}")
    print(f"{'seconds per episode':<24}mean {np.mean(seconds):.2f}, max {np.max(seconds):.2f}")
    print(f"{'steps per episode':<24}mean {np.mean(steps):.1f}, max {np.max(steps)}")
    print(f"{'push library build':<24}{library_seconds:.2f} s (once per process)")
    print(f"{'failed seeds':<24}{failed_seeds or 'none'}")


if __name__ == "__main__":
    main()
