"""The control services: the processes of the teleoperation loop (puma, force,
decision, master, vision) and the passivity controllers they share."""
