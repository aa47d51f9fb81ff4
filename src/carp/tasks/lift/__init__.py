"""Lift: lift the cube off the table (robosuite's ``Lift``); its task object (`task`) and scripted expert (`expert`)."""
