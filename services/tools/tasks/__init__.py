"""The paper's three evaluation tasks as simulated scenarios (docs/tasks.md)."""
