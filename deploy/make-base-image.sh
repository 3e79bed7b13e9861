#!/usr/bin/env bash
# make-base-image.sh: a base image for deploy/Dockerfile made from Debian's own packages,
# for a Docker host that reaches no image registry (no Docker Hub, no mirror of it).
#
#   deploy/make-base-image.sh [-t TAG] [-m MIRROR] [-s SUITE] [--ca FILE]...
#   docker build -f deploy/Dockerfile --build-arg BASE=TAG -t telerobot:0.1 .
#
# What the official python:3.11-slim-bookworm image gives the Dockerfile, from Debian
# bookworm's packages instead: a minimal Debian (debootstrap --variant=minbase), Python 3.11
# with pip that installs into /usr/local as root (Debian's "externally managed" marker
# removed, as in the official image, whose Python is its own), and the tools the Dockerfile
# runs (apt-get, groupadd/useradd). Imported with `docker import`; nothing is pulled.
#
# -t TAG     the image to make (default telerobot-base:3.11-bookworm)
# -m MIRROR  the Debian mirror debootstrap and the image's apt use
#            (default http://deb.debian.org/debian)
# -s SUITE   the Debian release (default bookworm: Python 3.11, as the official image)
# --ca FILE  a CA certificate (PEM) the image trusts besides Debian's, e.g. the one of a
#            site's TLS-inspecting proxy, so that pip inside `docker build` reaches PyPI
#            (repeatable; none by default)
#
# Needs root, debootstrap (apt-get install debootstrap) and a running Docker engine.
# Takes about a minute; the image is about 150 MB.
set -euo pipefail

usage() {
  sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit "${1:-2}"
}

die() {
  echo "make-base-image.sh: $*" >&2
  exit 2
}

tag="telerobot-base:3.11-bookworm"
mirror="http://deb.debian.org/debian"
suite="bookworm"
cas=()
while [ "$#" -gt 0 ]; do
  case "$1" in
    -h | --help) usage 0 ;;
    -t | -m | -s | --ca)
      [ "$#" -ge 2 ] && [ -n "$2" ] || die "$1 needs a value"
      case "$1" in
        -t) tag="$2" ;;
        -m) mirror="$2" ;;
        -s) suite="$2" ;;
        --ca)
          [ -f "$2" ] || die "--ca $2: no such file"
          grep -q -- "-----BEGIN CERTIFICATE-----" "$2" || die "--ca $2: not a PEM certificate"
          cas+=("$2")
          ;;
      esac
      shift 2
      ;;
    *) die "unknown argument '$1' (-h: help)" ;;
  esac
done
[ "$(id -u)" = 0 ] || die "needs root (debootstrap)"
command -v debootstrap >/dev/null || die "needs debootstrap (apt-get install debootstrap)"
command -v docker >/dev/null || die "needs the docker client and a running engine"
docker info >/dev/null 2>&1 || die "no Docker engine answers (start dockerd first)"

root="$(mktemp -d /var/tmp/telerobot-base.XXXXXX)"
trap 'rm -rf "$root"' EXIT
# the image's / is this folder: 0755 as in any image (mktemp makes it 0700, and then no
# user but root could run anything in the container)
chmod 0755 "$root"

# passwd: groupadd/useradd; python3-pip pulls setuptools and wheel; libudev1 and
# libusb-1.0-0 are what the Dockerfile installs anyway (hidapi loads them).
packages="passwd,ca-certificates,python3,python3-pip,python3-venv,python-is-python3,libudev1,libusb-1.0-0"
echo "debootstrap $suite ($mirror) into $root"
debootstrap --variant=minbase --include="$packages" "$suite" "$root" "$mirror" >"$root.log" 2>&1 \
  || { tail -20 "$root.log" >&2; rm -f "$root.log"; die "debootstrap failed"; }
rm -f "$root.log"

# The image's apt sources: the release, its updates and its security fixes.
security="${mirror%/debian}/debian-security"
cat >"$root/etc/apt/sources.list" <<EOF
deb $mirror $suite main
deb $mirror $suite-updates main
deb $security $suite-security main
EOF

# pip as root installs into /usr/local, like the official image's own Python.
rm -f "$root"/usr/lib/python3*/EXTERNALLY-MANAGED

# which script made it: a test reuses a base only if this very script made it
env_changes=(--change "LABEL org.telerobot.base-script=$(sha256sum "$0" | cut -c1-64)"
  --change "ENV LANG=C.UTF-8"
  --change "ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin")
if [ "${#cas[@]}" -gt 0 ]; then
  mkdir -p "$root/usr/local/share/ca-certificates"
  for ca in "${cas[@]}"; do
    name="$(basename "$ca")"
    cp "$ca" "$root/usr/local/share/ca-certificates/${name%.*}.crt"
  done
  chroot "$root" update-ca-certificates >/dev/null 2>&1 || die "update-ca-certificates failed"
  # pip's own bundle does not know them: point it at the system's
  env_changes+=(--change "ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt")
fi

apt-get -o "Dir=$root" clean 2>/dev/null || true
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/var/log/*.log \
  "$root"/tmp/* "$root"/root/.cache
python="$(chroot "$root" python3 --version)"
pip="$(chroot "$root" python3 -m pip --version | cut -d' ' -f1-2)"

tar --numeric-owner -C "$root" -c . \
  | docker import "${env_changes[@]}" --change 'CMD ["python3"]' \
    --message "Debian $suite minbase + $python + $pip (deploy/make-base-image.sh)" - "$tag" \
    >/dev/null
echo "made $tag from Debian $suite packages: $python, $pip${cas:+, ${#cas[@]} extra CA(s)}"
echo "build with: docker build -f deploy/Dockerfile --build-arg BASE=$tag -t telerobot:0.1 ."
