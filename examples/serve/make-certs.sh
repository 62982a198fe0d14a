#!/bin/sh
# A certificate authority, a server certificate and a client certificate for
# server-auth.json5 and client-auth.json5 (mutual TLS), made with openssl:
#
#     sh examples/serve/make-certs.sh DIR [SERVER_NAMES]
#
# SERVER_NAMES: the names clients connect to (default DNS:localhost,IP:127.0.0.1).
# Keep ca-key.pem offline; give each host only its own key and ca.pem.
set -eu
dir=${1:?usage: make-certs.sh DIR [SERVER_NAMES]}
names=${2:-DNS:localhost,IP:127.0.0.1}
mkdir -p "$dir"
cd "$dir"
ec="-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes"
openssl req -x509 $ec -days 365 -subj "/CN=motorbus CA" -keyout ca-key.pem -out ca.pem
openssl req $ec -subj "/CN=motorbus server" -keyout server-key.pem -out server.csr
printf 'basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\nsubjectAltName=%s\n' \
    "$names" > server.ext
openssl x509 -req -in server.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 365 \
    -extfile server.ext -out server-cert.pem
openssl req $ec -subj "/CN=motorbus client" -keyout client-key.pem -out client.csr
printf 'basicConstraints=CA:FALSE\nextendedKeyUsage=clientAuth\n' > client.ext
openssl x509 -req -in client.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 365 \
    -extfile client.ext -out client-cert.pem
rm -f server.csr server.ext client.csr client.ext ca.srl
