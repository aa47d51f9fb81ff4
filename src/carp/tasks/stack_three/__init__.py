"""StackThree: a tower of three cubes, carp's env on robosuite's Stack.

`env` defines the env (importing it registers ``StackThree`` with robosuite), `task` the task object and `expert` the
scripted expert.
"""
