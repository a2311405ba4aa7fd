#!/usr/bin/env bash
# Refreshes the Swagger UI assets /docs serves (service/static/swagger/) from the npm package swagger-ui-dist,
# Swagger UI's own prebuilt distribution (SmartBear, Apache-2.0). Needs npm and the npm registry; run by hand when
# upgrading, never at build or run time (the server serves these files itself: /docs works without internet).
#   bash service/static/swagger/fetch.sh [VERSION]      (default: the version in VERSION beside this script)
# Swagger UI 5.x reads OpenAPI 3.1, the version FastAPI publishes (4.x shows "Unable to render this definition").
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
version="${1:-$(cat "$here/VERSION")}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm pack --silent "swagger-ui-dist@$version" > /dev/null)
tar -xzf "$tmp/swagger-ui-dist-$version.tgz" -C "$tmp"
# the bundle (with its third-party notices), its stylesheet, the icon, and the package's licence and notice
for f in swagger-ui-bundle.js swagger-ui-bundle.js.LICENSE.txt swagger-ui.css favicon-32x32.png LICENSE NOTICE; do
  install -m 0644 "$tmp/package/$f" "$here/$f"
done
echo "$version" > "$here/VERSION"
(cd "$here" && sha256sum swagger-ui-bundle.js swagger-ui.css > SHA256SUMS)
# the script is kept gzipped (served with Content-Encoding: gzip; -n: no name or time, so it does not churn)
gzip -9nf "$here/swagger-ui-bundle.js"
echo "swagger-ui-dist $version -> $here"
