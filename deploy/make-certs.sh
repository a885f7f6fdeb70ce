#!/usr/bin/env bash
# Throwaway certificates for trying the TLS/mTLS example (deploy/zenohd-tls.json5,
# deploy/client-tls.json5) on a test bench. FOR LOCAL TESTING ONLY: the CA key is left on disk
# next to the certificates, keys are unencrypted, nothing here is fit for a real fleet.
#
#   deploy/make-certs.sh [OUT_DIR] [CLIENT ...]
#
# OUT_DIR defaults to deploy/certs. Writes
#   ca.pem, ca-key.pem                  the throwaway certificate authority
#   zenohd.pem, zenohd-key.pem          router certificate (CN zenohd; SAN zenohd, localhost,
#                                       127.0.0.1; extended key usage serverAuth)
#   <client>.pem, <client>-key.pem      one client certificate per CLIENT (CN = the name, which
#                                       the router's ACL matches with `cert_common_names`;
#                                       extended key usage clientAuth)
# CLIENTs default to: auv1 auv2 mergesvc bridge. Needs openssl (1.1.1 or 3.x).
set -euo pipefail

out="${1:-$(dirname "$0")/certs}"
shift || true
clients=("$@")
if [ ${#clients[@]} -eq 0 ]; then
  clients=(auv1 auv2 mergesvc bridge)
fi
days=30

mkdir -p "$out"
cd "$out"
# keep throwaway keys out of git
printf '*\n' >.gitignore

new_key() { # $1: key file (PKCS#8, EC P-256)
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

# Certificate authority
new_key ca-key.pem
openssl req -x509 -new -key ca-key.pem -sha256 -days "$days" -subj "/CN=mergesvc test CA" \
  -addext "basicConstraints=critical,CA:TRUE" \
  -addext "keyUsage=critical,keyCertSign,cRLSign" \
  -out ca.pem

sign() { # $1: name (CN and file stem), $2: extended key usage, $3: subjectAltName
  local name="$1" eku="$2" san="$3" ext
  new_key "$name-key.pem"
  openssl req -new -key "$name-key.pem" -subj "/CN=$name" -out "$name.csr"
  ext="$(mktemp)"
  {
    echo "basicConstraints=critical,CA:FALSE"
    echo "keyUsage=critical,digitalSignature"
    echo "extendedKeyUsage=$eku"
    echo "subjectAltName=$san"
  } >"$ext"
  openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -sha256 \
    -days "$days" -extfile "$ext" -out "$name.pem" 2>/dev/null
  rm -f "$name.csr" "$ext"
}

sign zenohd serverAuth "DNS:zenohd,DNS:localhost,IP:127.0.0.1"
for c in "${clients[@]}"; do
  sign "$c" clientAuth "DNS:$c"
done
rm -f ca.srl
# everything readable, keys included: the mergesvc container runs as a non-root user and must
# read its bind-mounted key (throwaway keys; protect real ones with 0600 and the right owner)
chmod 644 ./*.pem

echo "wrote $(pwd): ca.pem zenohd.pem ${clients[*]/%/.pem} (and their -key.pem)"
