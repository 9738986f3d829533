#!/usr/bin/env bash
# Refresh service/static/vendor/three/ from the three.js pinned in web/package.json and
# web/package-lock.json (`make vendor`). The page loads these files from the API, never a CDN.
# To move to another release: change the pin in package.json, `npm install` here to update the
# lock file, then run this.
set -euo pipefail
cd "$(dirname "$0")"
npm ci --no-audit --no-fund
src=node_modules/three
dst=../service/static/vendor/three
version=$(node -p "require('./$src/package.json').version")
rm -rf "$dst"
mkdir -p "$dst"
cp "$src/build/three.module.js" "$src/build/three.core.js" \
   "$src/examples/jsm/controls/OrbitControls.js" "$src/LICENSE" "$dst/"
cat > "$dst/VERSION" <<END
three $version
npm package three@$version, unmodified: build/three.module.js, build/three.core.js,
examples/jsm/controls/OrbitControls.js and LICENSE (MIT). Refreshed by web/vendor.sh.
END
echo "service/static/vendor/three: three $version"
