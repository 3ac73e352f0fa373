#!/usr/bin/env bash
# Test certificates for a sinewatch deployment with mutual TLS (deploy/zenoh-router-tls.json5).
# One CA; one certificate per role, told apart by its Common Name, which the router's
# access-control subjects match: router, sinewatch-daemon, gateway, reader.
# For tests and trials only: a real deployment issues these from its own PKI.
#
#   deploy/tls/make-certs.sh DIR     # writes DIR/ca.pem and DIR/<role>.pem + DIR/<role>-key.pem
set -euo pipefail
dir=${1:?usage: make-certs.sh DIR}
days=${DAYS:-30}
mkdir -p "$dir"
cd "$dir"
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days "$days" \
  -subj "/CN=sinewatch-test-ca" -keyout ca-key.pem -out ca.pem 2>/dev/null
for role in router sinewatch-daemon gateway reader; do
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
    -subj "/CN=$role" -keyout "$role-key.pem" -out "$role.csr" 2>/dev/null
  printf 'subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth,clientAuth\n' > "$role.ext"
  openssl x509 -req -in "$role.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days "$days" \
    -extfile "$role.ext" -out "$role.pem" 2>/dev/null
  rm -f "$role.csr" "$role.ext"
done
rm -f ca.srl
chmod 600 ./*-key.pem
echo "certificates for router, sinewatch-daemon, gateway, reader in $dir"
