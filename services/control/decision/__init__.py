"""The decision service: the paper's DecisionServer, supervisor between the masters and the
arm and the operator's single entry point (docs/decision.md).

Pure, free of I/O: `supervisor` (one `tick()` per input and per timer wake-up), `target`
(the supervised target shaped from the operator's or a task's goal), `filters` (contact,
admittance, limits), `watchdogs` (freshness of every stream), `masters` (each master's
seq, engagement and lease), `notices` (its events, queued and rate-limited), `tasks` and
`taskrun` (the autonomous functions and their runs), `watch` (forwarded motions watched
and stopped at a contact or a face). On the bus: `service` (IDecisionServer), `forcefeed`
(robot/force only while the arm may move), `peeks` (the other services' status),
`passivity` (TDPA's slave side). `config` is the `[decision]` table.
"""
