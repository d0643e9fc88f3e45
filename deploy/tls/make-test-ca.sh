#!/usr/bin/env bash
# Make a test certificate authority and one certificate per router, for mutual TLS
# (over QUIC, `quic/` endpoints) between the routers of a GEESE swarm
# (deploy/MULTI-HOST.md). For tests and trials:
# in production, have your own CA sign the routers' keys.
#
#   deploy/tls/make-test-ca.sh OUT_DIR NAME=IP[,IP...] [NAME=IP...]
#
# writes OUT_DIR/ca.pem (the authority every router trusts), and for each NAME
# OUT_DIR/NAME.pem and OUT_DIR/NAME.key: a certificate whose common name is
# `router-NAME` (the subject `geese secure init --routers NAME` writes), valid for
# the listed IP addresses (checked when a router connects to it), usable both to accept
# links (serverAuth) and to open them (clientAuth). Keys are readable by their owner only.
set -euo pipefail
if [ $# -lt 2 ]; then
  echo "usage: $0 OUT_DIR NAME=IP[,IP...] [NAME=IP[,IP...] ...]" >&2
  exit 2
fi
out=$1
shift
mkdir -p "$out"
umask 077
days=30
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days "$days" \
  -subj "/CN=GEESE test CA" -keyout "$out/ca.key" -out "$out/ca.pem" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
for spec in "$@"; do
  name=${spec%%=*}
  ips=${spec#*=}
  if [ -z "$name" ] || [ "$name" = "$spec" ] || ! [[ $name =~ ^[A-Za-z0-9._-]+$ ]]; then
    echo "$0: $spec: expected NAME=IP[,IP...] with NAME of letters, digits, '.', '_', '-'" >&2
    exit 2
  fi
  san=""
  IFS=, read -ra list <<<"$ips"
  for ip in "${list[@]}"; do
    san="${san:+$san,}IP:$ip"
  done
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -subj "/CN=router-$name" \
    -keyout "$out/$name.key" -out "$out/$name.csr" 2>/dev/null
  openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
    -days "$days" -out "$out/$name.pem" \
    -extfile <(printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\nkeyUsage=critical,digitalSignature\nbasicConstraints=CA:FALSE\n' "$san") 2>/dev/null
  rm -f "$out/$name.csr"
  echo "$out/$name.pem: CN=router-$name, $san"
done
chmod 644 "$out"/*.pem
echo "$out/ca.pem: the authority (its key $out/ca.key signs nothing else; delete it when done)"
