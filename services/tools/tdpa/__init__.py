"""TDPA's lab: the bilateral loop over a bad link, simulated and for real, and its benches.

`loop` closes the whole position–force loop in simulation (hand, device, link, slave,
wall, both passivity controllers; pure, seeded), `sim_bench` (`telerobot bench passivity`)
runs it TDPA off and on per delay into a table, a JSON and plots, `link_bench`
(`telerobot bench passivity --link`) runs the same task through the real services over the
emulated link, `results` is what both write (a run's measures under their JSON keys, the
off/on plot). The emulated link: `netem` (network namespaces joined by the kernel's netem
or by the delay line), `delayline` (the userspace delay line, a TUN device), `transports`
(each Zenoh transport's endpoint across it, TLS files for the secure ones). The ports
themselves run in the services (services.control.passivity and its hooks);
`telerobot bench link` (services.tools.bench.link) uses this link too. docs/passivity.md.
"""
