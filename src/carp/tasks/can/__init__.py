"""Can: the can into its bin (robosuite's ``PickPlaceCan``); its task object (`task`) and scripted expert (`expert`)."""
