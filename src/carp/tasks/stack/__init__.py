"""Stack: the small cube onto the large one (robosuite's ``Stack``).

`task` holds the task object; `expert` the scripted expert, whose move StackThree's expert repeats.
"""
