#!/usr/bin/env bash
# Fetch three.js from the npm registry (npm pack: the published tarball, its integrity checked
# by npm) and copy its self-contained ES module build and licence into the console's static
# files, where they are committed: the console loads no script from elsewhere at run time.
# Usage: scripts/vendor-three.sh (needs npm); run again only to change THREE_VERSION.
set -euo pipefail
cd "$(dirname "$0")/.."
THREE_VERSION=0.170.0  # the last release whose build/ has three.module.min.js in one file
# sha256 of three-0.170.0.tgz as the registry serves it
THREE_SHA256=4a608a355dcaba72e0e5383cdc814303f5b6060b43c238cdf6932dceb699238d
vendor=service/console/static/vendor
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
(cd "$scratch" && npm pack --silent "three@$THREE_VERSION" >/dev/null)
tarball="$scratch/three-$THREE_VERSION.tgz"
echo "$THREE_SHA256  $tarball" | sha256sum --check --quiet
tar -xzf "$tarball" -C "$scratch" package/build/three.module.min.js package/LICENSE
mkdir -p "$vendor"
cp "$scratch/package/build/three.module.min.js" "$vendor/three.module.min.js"
cp "$scratch/package/LICENSE" "$vendor/three.LICENSE"
echo "three.js $THREE_VERSION -> $vendor"
