"""Telerobot: every service, model and tool, in layers whose imports only point down
(docs/architecture.md): `geometry` <- `bus` <- `world` <- `control` <- `frontends` <- `tools`."""
