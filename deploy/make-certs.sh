#!/usr/bin/env bash
# Make a private CA and certificates for silcr's Zenoh links (TLS, mutual TLS, access control).
#
#   deploy/make-certs.sh DIR ROUTER_HOST [ROUTER_HOST ...]
#
# Writes into DIR:
#   ca.pem / ca.key                 the CA (keep ca.key offline; every machine needs ca.pem)
#   router.pem / router.key         the router's certificate, valid for the ROUTER_HOST names/IPs
#   <role>.pem / <role>.key         one client identity per role: learner, buffer, actor, monitor.
#                                   The certificate's common name (CN) is silcr-<role>; the router's
#                                   access control (deploy/zenoh/router-tls-acl.json5) grants rights
#                                   by that name, so hand actor.* only to actor machines.
set -euo pipefail
if [ $# -lt 2 ]; then
    echo "usage: $0 DIR ROUTER_HOST [ROUTER_HOST ...]   (host names or IP addresses of the router)" >&2
    exit 2
fi
dir="$1"; shift
mkdir -p "$dir"
cd "$dir"
days=825

openssl req -x509 -newkey rsa:2048 -nodes -keyout ca.key -out ca.pem -days "$days" \
    -subj "/CN=silcr-ca" -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null

san=""
for h in "$@"; do
    if [[ "$h" =~ ^[0-9.]+$ || "$h" == *:* ]]; then san="${san:+$san,}IP:$h"; else san="${san:+$san,}DNS:$h"; fi
done

issue() {  # name CN extensions
    openssl req -newkey rsa:2048 -nodes -keyout "$1.key" -out "$1.csr" -subj "/CN=$2" 2>/dev/null
    printf '%s\n' "$3" > "$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$1.pem" -days "$days" \
        -extfile "$1.ext" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}

issue router silcr-router "subjectAltName=$san
extendedKeyUsage=serverAuth,clientAuth"
for role in learner buffer actor monitor; do
    # Clients also listen in peer mode, so they get serverAuth as well; the SAN lets them be verified.
    issue "$role" "silcr-$role" "subjectAltName=$san,DNS:silcr-$role
extendedKeyUsage=clientAuth,serverAuth"
done
rm -f ca.srl
chmod 600 ./*.key
echo "certificates for ${*} written to $dir"
