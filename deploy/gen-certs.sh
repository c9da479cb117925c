#!/usr/bin/env bash
# Make a private CA, a server certificate for the router's TLS listener, and a client certificate
# for mutual TLS:
#   bash gen-certs.sh OUT_DIR ROUTER_HOST_OR_IP [CLIENT_NAME]
# writes OUT_DIR/{ca.pem,ca.key,server.pem,server.key,client.pem,client.key}.
# Zenoh (rustls) rejects a CA certificate used as the server's own (CaUsedAsEndEntity): the server
# certificate is a leaf (CA:FALSE) signed by the CA, with the router's host in its subjectAltName,
# which must match the host in the clients' tls/HOST:PORT endpoint.
set -euo pipefail
out="${1:?usage: gen-certs.sh OUT_DIR HOST [CLIENT_NAME]}"; host="${2:?usage: gen-certs.sh OUT_DIR HOST [CLIENT_NAME]}"
client="${3:-visfly-client}"
mkdir -p "$out"; cd "$out"
if [[ "$host" =~ ^[0-9.]+$ ]]; then san="IP:$host"; else san="DNS:$host"; fi
openssl req -x509 -newkey rsa:2048 -nodes -days 825 -subj "/CN=visfly-dist CA" \
  -keyout ca.key -out ca.pem -addext "basicConstraints=critical,CA:TRUE" 2>/dev/null
leaf() {  # leaf NAME CN EXTRA_EXTENSIONS
  openssl req -newkey rsa:2048 -nodes -subj "/CN=$2" -keyout "$1.key" -out "$1.csr" 2>/dev/null
  printf "basicConstraints=critical,CA:FALSE\n%s\n" "$3" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 \
    -extfile "$1.ext" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}
leaf server "$host" "subjectAltName=$san"
leaf client "$client" "extendedKeyUsage=clientAuth"
rm -f ca.srl
chmod 600 ca.key server.key client.key
echo "wrote $out/{ca.pem,ca.key,server.pem,server.key,client.pem,client.key}: server for $san, client CN=$client"
