#!/usr/bin/env bash
# Make a private CA and a server certificate for the router's TLS listener.
#   bash gen-certs.sh OUT_DIR HOSTNAME_OR_IP
# Zenoh (rustls) rejects a CA certificate used as the server's own (CaUsedAsEndEntity): the server
# certificate is a leaf (CA:FALSE) signed by the CA, with the host in its subjectAltName.
set -euo pipefail
out="${1:?usage: gen-certs.sh OUT_DIR HOST}"; host="${2:?usage: gen-certs.sh OUT_DIR HOST}"
mkdir -p "$out"; cd "$out"
if [[ "$host" =~ ^[0-9.]+$ ]]; then san="IP:$host"; else san="DNS:$host"; fi
openssl req -x509 -newkey rsa:2048 -nodes -days 825 -subj "/CN=visfly-dist CA" \
  -keyout ca.key -out ca.pem -addext "basicConstraints=critical,CA:TRUE" 2>/dev/null
openssl req -newkey rsa:2048 -nodes -subj "/CN=$host" -keyout server.key -out server.csr 2>/dev/null
printf "basicConstraints=critical,CA:FALSE\nsubjectAltName=%s\n" "$san" > ext.cnf
openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 \
  -extfile ext.cnf -out server.pem 2>/dev/null
rm -f server.csr ext.cnf ca.srl
echo "wrote $out/{ca.pem,ca.key,server.pem,server.key} for $san"
