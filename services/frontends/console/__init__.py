"""The operator console: a web page that mirrors the arm, shows stereo video and force, and
drives the system through the decision server and a (virtual) master. See docs/console.md."""
