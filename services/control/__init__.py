"""The control services: the processes of the teleoperation loop (arm, force,
decision, master, vision) and the passivity controllers they share."""
