"""Push-T: Diffusion Policy's planar pushing task on gym-pusht.

`env` is DP's state-based protocol around gym-pusht's simulation (observation, seeded reset, reward, success, step
limit), `task` the task object with its score measure, and `expert` the planning expert that collects its demos.
"""
