"""The CCE-MAPPO learner: losses, advantage estimation and risk measures (see ``losses``)."""
