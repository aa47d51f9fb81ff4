"""Tasks beside robosuite's arms: how to make, reset and score their environments (Push-T: `carp.tasks.pusht`)."""
