#!/bin/sh
# Make a small private PKI for the robot's Zenoh router and its remote hosts (mutual TLS), with openssl.
#
#   make-certs.sh DIR ca                      # the certificate authority: DIR/ca.pem + DIR/ca.key (keep ca.key offline)
#   make-certs.sh DIR NAME [SAN ...]          # DIR/NAME.pem + DIR/NAME.key, CN=NAME, signed by DIR/ca.*
#
# SAN entries are openssl subjectAltName items, e.g. DNS:zagv-r1.local IP:192.168.10.20. The router's certificate
# must name every address clients dial (rustls checks the SAN, never the CN); a client's CN is what the router's
# access control matches (subjects/cert_common_names). Keys are EC P-256 in PKCS#8, certificates are valid for
# serverAuth and clientAuth, for $ZAGV_CERT_DAYS days (default 825).
set -eu

usage() {
    echo "usage: $0 DIR ca | $0 DIR NAME [SAN ...]   (SAN like DNS:host or IP:192.168.10.20)" >&2
    exit 2
}
[ $# -ge 2 ] || usage
dir=$1
name=$2
shift 2
days=${ZAGV_CERT_DAYS:-825}
mkdir -p "$dir"
umask 077

if [ "$name" = ca ]; then
    [ $# -eq 0 ] || usage
    if [ -e "$dir/ca.pem" ]; then
        echo "$dir/ca.pem exists; not replacing the certificate authority" >&2
        exit 1
    fi
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/ca.key"
    openssl req -x509 -new -key "$dir/ca.key" -sha256 -days "$days" -subj "/CN=zagv-ca" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$dir/ca.pem"
    chmod 644 "$dir/ca.pem"
    echo "wrote $dir/ca.pem (share) and $dir/ca.key (secret)"
    exit 0
fi

case $name in
    */* | .* | "") echo "certificate name '$name' must be a plain file name" >&2; exit 2 ;;
esac
[ -e "$dir/ca.pem" ] && [ -e "$dir/ca.key" ] || { echo "no CA in $dir: run '$0 $dir ca' first" >&2; exit 1; }

san="DNS:$name"
for item in "$@"; do
    case $item in
        DNS:* | IP:*) san="$san,$item" ;;
        *) echo "SAN '$item' must start with DNS: or IP:" >&2; exit 2 ;;
    esac
done

ext=$(mktemp)
trap 'rm -f "$ext" "$dir/$name.csr"' EXIT
cat >"$ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyAgreement
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san
EOF
openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/$name.key"
openssl req -new -key "$dir/$name.key" -subj "/CN=$name" -out "$dir/$name.csr"
openssl x509 -req -in "$dir/$name.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" -CAcreateserial \
    -days "$days" -sha256 -extfile "$ext" -out "$dir/$name.pem" 2>/dev/null
chmod 644 "$dir/$name.pem"
echo "wrote $dir/$name.pem and $dir/$name.key (CN=$name, SAN $san)"
