# zenohd in an image of our own, for a host that cannot pull eclipse/zenoh: the binary that
# `make zenohd` builds with `cargo install zenohd` (dynamically linked against the build
# host's glibc: build it on the Debian release of BASE). The context is a folder holding
# only that binary:
#
#   docker build -f deploy/zenohd.Dockerfile --build-arg BASE=telerobot-base:3.11-bookworm \
#     -t telerobot-zenohd:1.10.2 DIR-WITH-zenohd
#
# Like eclipse/zenoh, its arguments are zenohd's (`-c /etc/telerobot/zenoh/robot-router.json5`
# in deploy/compose/robot.yml), and it runs as root as that image does, with no capability
# (robot.yml's cap_drop): root reads the root:telerobot 0640 site files as their owner.
ARG BASE=debian:bookworm-slim
FROM ${BASE}
COPY zenohd /usr/local/bin/zenohd
ENTRYPOINT ["/usr/local/bin/zenohd"]
