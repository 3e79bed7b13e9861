"""The simulated world: the one description of the workcell (objects, table, liquid),
which the simulated force sensor touches and vision and the console draw."""
