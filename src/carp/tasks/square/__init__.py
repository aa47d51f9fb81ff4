"""Square: the square nut onto its peg (robosuite's ``NutAssemblySquare``).

`task` holds the task object, measured by the nut's insertion offset; `expert` the scripted expert, whose nut moves
NutAssembly's expert shares.
"""
