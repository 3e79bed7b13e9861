#!/usr/bin/env bash
# make-certs.sh: a private certificate authority and the certificates of one Telerobot cell.
#
#   deploy/certs/make-certs.sh [-o DIR] [-d DAYS] [-c CLIENT]... ROBOT_HOST [ROBOT_HOST...]
#
# Options may come anywhere (`make-certs.sh robot.lab.example 10.0.0.5 -c operator1` works);
# anything else that starts with "-" is refused, and nothing is written.
#
# ROBOT_HOST: every name or address an operator will use to reach the robot host's router
#   (tls/ROBOT_HOST:7448), e.g. `robot.lab.example.org 192.168.10.5`. Each one goes into the
#   router certificate's subjectAltName (DNS or IP), because clients check the name they dialled
#   against it (Zenoh's `verify_name_on_connect`, on by default).
# -c CLIENT: a client certificate CLIENT.pem (repeatable; default: operator and observer).
#   Its common name is the role the router's ACL matches (`cert_common_names`, with the
#   login of the same name): a CLIENT that starts with `operator` or `observer`
#   (operator1, observer-lab2) gets that role as its CN and its own name as its OU; any
#   other CLIENT is its own CN (add it to the ACL's `cert_common_names` to let it in).
# -o DIR: where to write (default: the current directory). An existing CA there is reused, so
#   the script can be run again to add a client or renew the router certificate without
#   re-issuing everyone's.
# -d DAYS: validity of the new leaf certificates (default 825, the longest most clients accept).
## The certificates serve TLS and QUIC alike (QUIC carries TLS 1.3 and reads the same files).
#
# Writes, in DIR: ca.pem, ca.key (keep the key offline), router.pem, router.key, and
# CLIENT.pem, CLIENT.key per client. Keys are ECDSA P-256 in PKCS#8, which Zenoh (rustls) reads.
set -euo pipefail

usage() {
  sed -n '2,25p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit "${1:-2}"
}

die() {
  echo "make-certs.sh: $*" >&2
  echo "usage: make-certs.sh [-o DIR] [-d DAYS] [-c CLIENT]... ROBOT_HOST [ROBOT_HOST...] (-h: help)" >&2
  exit 2
}

# Options may come before, between or after the host names (the README writes
# `make-certs.sh robot.lab.example 10.0.0.5 -c operator1`); getopts would stop at the first
# host and put "-c" and "operator1" into the router certificate. `--` ends the options.
out="."
days=825
clients=()
hosts=()
while [ "$#" -gt 0 ]; do
  case "$1" in
    -h | --help) usage 0 ;;
    -o | -d | -c)
      [ "$#" -ge 2 ] && [ -n "$2" ] && [ "${2#-}" = "$2" ] || die "$1 needs a value"
      case "$1" in
        -o) out="$2" ;;
        -d) days="$2" ;;
        -c) clients+=("$2") ;;
      esac
      shift 2
      ;;
    -o?* | -d?* | -c?*) set -- "${1:0:2}" "${1:2}" "${@:2}" ;;  # -coperator1 → -c operator1
    --)
      shift
      hosts+=("$@")
      break
      ;;
    -*) die "unknown option '$1'" ;;
    *)
      hosts+=("$1")
      shift
      ;;
  esac
done
[ "${#hosts[@]}" -ge 1 ] || die "give at least one ROBOT_HOST (the robot's name or address)"
for host in "${hosts[@]}"; do
  case "$host" in
    '' | -* | *[!A-Za-z0-9.:-]*) die "'$host' is not a host name or an IP address" ;;
  esac
done
set -- "${hosts[@]}"
[ "${#clients[@]}" -gt 0 ] || clients=(operator observer)
command -v openssl >/dev/null || { echo "make-certs.sh: needs openssl (apt-get install openssl)" >&2; exit 1; }
case "$days" in '' | *[!0-9]*) die "-d takes a number of days" ;; esac
for client in "${clients[@]}"; do
  case "$client" in
    '' | *[!A-Za-z0-9._-]*) die "bad client name '$client'" ;;
    router | ca) die "'$client' is reserved" ;;
  esac
done

mkdir -p "$out"
umask 077  # private keys readable by their owner only
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

# subjectAltName entries: an IPv4/IPv6 literal is an IP entry, anything else a DNS name.
san=""
for host in "$@"; do
  case "$host" in
    *[!0-9.]* | '') if [[ "$host" == *:* ]]; then entry="IP:$host"; else entry="DNS:$host"; fi ;;
    *) entry="IP:$host" ;;
  esac
  san="${san:+$san,}$entry"
done

newkey() {
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

if [ -f "$out/ca.pem" ] && [ -f "$out/ca.key" ]; then
  echo "reusing the CA in $out"
else
  newkey "$out/ca.key"
  # The CA lives longer than its leaves (10 years); rustls requires CA:TRUE and keyCertSign.
  openssl req -x509 -new -key "$out/ca.key" -sha256 -days 3650 -subj "/CN=Telerobot cell CA" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -addext "subjectKeyIdentifier=hash" \
    -out "$out/ca.pem"
  echo "new CA: $out/ca.pem"
fi

# sign NAME SUBJECT EXTENSIONS [NOTE]: NAME.key + NAME.pem signed by the CA.
sign() {
  local name="$1" subj="$2" ext="$3"
  newkey "$out/$name.key"
  openssl req -new -key "$out/$name.key" -subj "$subj" -out "$work/$name.csr"
  printf '%b\n' "$ext" >"$work/$name.ext"
  # -CAcreateserial with a fresh serial file: a random serial number per certificate
  openssl x509 -req -in "$work/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" \
    -CAcreateserial -CAserial "$work/ca.srl" -sha256 -days "$days" \
    -extfile "$work/$name.ext" -out "$out/$name.pem" 2>/dev/null
  echo "$name.pem: ${subj#/}${4:+, $4}"
}

leaf="basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nsubjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid"
sign router /CN=telerobot-router "$leaf\nextendedKeyUsage=serverAuth\nsubjectAltName=$san" "SAN $san"
# A station's certificate names its role (the ACL's cert_common_names and the login of the
# same name in users.txt); the station itself is the OU, so `-c operator1` and `-c operator2`
# both command and stay apart in the certificates.
for client in "${clients[@]}"; do
  case "$client" in
    operator | observer) subj="/CN=$client" note="" ;;
    operator* | observer*)
      role="${client:0:8}"
      subj="/OU=$client/CN=$role"
      note="the ACL's $role role: install as $role.pem/$role.key on that station"
      ;;
    *) subj="/CN=$client" note="not a shipped role: add $client to an ACL subject's cert_common_names" ;;
  esac
  sign "$client" "$subj" "$leaf\nextendedKeyUsage=clientAuth" "$note"
done

# Certificates are public; keys stay 0600. Group-readable keys are set by the installer.
chmod 0644 "$out"/*.pem
openssl verify -CAfile "$out/ca.pem" "$out/router.pem" >/dev/null
echo "done: copy ca.pem, router.pem, router.key to the robot host;" \
  "ca.pem and a client's .pem/.key to its host"
