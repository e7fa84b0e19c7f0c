#!/bin/sh
# Make a private CA and the certificates of a dqm deployment with mutual TLS.
#
#   deploy/make-certs.sh OUTDIR ROUTER_NAMES CLIENT_NAME...
#
#   ROUTER_NAMES  comma-separated IP addresses and/or DNS names by which clients
#                 reach the router (they become the router certificate's
#                 subjectAltName; a client refuses a router whose certificate
#                 does not name the address in its tls/HOST:PORT endpoint)
#   CLIENT_NAME   one certificate per agent host / coordinator (e.g. agent0 coordinator)
#
# Writes OUTDIR/ca.pem (give to every process), OUTDIR/ca.key (keep it off the
# hosts), OUTDIR/router.{pem,key} and OUTDIR/<client>.{pem,key}. An existing
# OUTDIR/ca.pem + ca.key is reused, so clients can be added later. Keys are
# ECDSA P-256, certificates are valid for DAYS days (default 365).
#
# Example: deploy/make-certs.sh certs 192.0.2.10,router.lab agent0 agent1 coordinator
set -eu

if [ $# -lt 3 ]; then
    sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
fi
command -v openssl >/dev/null 2>&1 || { echo "make-certs.sh: openssl is not installed" >&2; exit 2; }
out=$1; router_names=$2; shift 2
days=${DAYS:-365}
mkdir -p "$out"
umask 077

san=""
old_ifs=$IFS; IFS=,
for n in $router_names; do
    case $n in
        *[!0-9.]*) case $n in *:*) entry="IP:$n" ;; *) entry="DNS:$n" ;; esac ;;
        *) entry="IP:$n" ;;
    esac
    san="${san:+$san,}$entry"
done
IFS=$old_ifs

newkey() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

if [ ! -f "$out/ca.pem" ] || [ ! -f "$out/ca.key" ]; then
    newkey "$out/ca.key"
    openssl req -x509 -new -key "$out/ca.key" -out "$out/ca.pem" -days "$days" -subj "/CN=dqm deployment CA" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
fi

# sign NAME EXTENSIONS: NAME.key + NAME.pem signed by the CA
sign() {
    newkey "$out/$1.key"
    openssl req -new -key "$out/$1.key" -out "$out/$1.csr" -subj "/CN=$1" 2>/dev/null
    printf '%s\n' "$2" > "$out/$1.ext"
    openssl x509 -req -in "$out/$1.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
        -out "$out/$1.pem" -days "$days" -extfile "$out/$1.ext" 2>/dev/null
    rm -f "$out/$1.csr" "$out/$1.ext"
}

sign router "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san"
for c in "$@"; do
    sign "$c" "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth
subjectAltName=DNS:$c"
done
chmod 644 "$out"/*.pem
echo "make-certs.sh: CA, router ($san) and $# client certificate(s) in $out"
