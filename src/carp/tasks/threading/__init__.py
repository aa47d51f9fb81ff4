"""Threading: a needle through a ring on a tripod, carp's env on robosuite.

`env` defines the env (importing it registers ``Threading`` with robosuite), `task` the task object, `insertion` the
needle-and-ring pair of its insertion-offset measure and `expert` the scripted expert.
"""
