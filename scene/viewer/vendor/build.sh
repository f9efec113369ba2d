#!/usr/bin/env bash
# Rebuild scene/viewer/vendor/three.min.js: three.js (MIT, see LICENSE here) with GLTFLoader and
# OrbitControls, bundled by esbuild into one minified IIFE that sets the global `HACKNECK_THREE`
# ({THREE, GLTFLoader, OrbitControls}).  Needs node + npm (the npm registry); writes only this folder.
#
#     bash scene/viewer/vendor/build.sh
set -euo pipefail
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --no-audit --no-fund --silent "three@${THREE_VERSION}" "esbuild@${ESBUILD_VERSION}"
cat > entry.js <<'JS'
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
export { THREE, GLTFLoader, OrbitControls };
JS
npx esbuild entry.js --bundle --minify --format=iife --global-name=HACKNECK_THREE \
    --legal-comments=none --target=es2020 \
    --banner:js="/* three.js ${THREE_VERSION} (MIT licence: LICENSE beside this file) + GLTFLoader + OrbitControls; built by build.sh with esbuild ${ESBUILD_VERSION} */" \
    --outfile=three.min.js
cp three.min.js "$here/three.min.js.tmp" && mv "$here/three.min.js.tmp" "$here/three.min.js"
cp node_modules/three/LICENSE "$here/LICENSE"
echo "$THREE_VERSION" > "$here/VERSION"
echo "wrote $here/three.min.js ($(wc -c < "$here/three.min.js") bytes), three ${THREE_VERSION}"
