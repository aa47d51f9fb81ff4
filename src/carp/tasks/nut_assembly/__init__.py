"""NutAssembly: both nuts onto their pegs (robosuite's ``NutAssembly``).

`task` holds the task object, measured by each nut's insertion offset; `expert` the scripted expert.
"""
