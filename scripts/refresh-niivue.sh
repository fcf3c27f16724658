#!/usr/bin/env bash
# Refresh the NiiVue bundle vendored into the package (the viewer's page
# loads it from the package, so installing spheroseg needs no Node and the
# page fetches nothing). Needs npm and the npm registry; run by a developer,
# never at install or run time:
#     scripts/refresh-niivue.sh [VERSION]      (default: the pinned one)
# Writes src/spheroseg/apps/viewer/static/vendor/: niivue.umd.js, VERSION (version,
# sha256, source), and LICENSES.txt (NiiVue's BSD-2-Clause and the licences of
# the packages its bundle includes). Pin a new version only after the
# browser tests (tests/test_viewer_page.py) pass with it: the page's contour
# overlay reads NiiVue's slice layout.
set -euo pipefail
VERSION="${1:-0.69.0}"
here="$(cd "$(dirname "$0")/.." && pwd)"
vendor="$here/src/spheroseg/apps/viewer/static/vendor"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm pack --silent "@niivue/niivue@$VERSION" >/dev/null
mkdir niivue && tar xzf niivue-niivue-"$VERSION".tgz -C niivue --strip-components=1
cp niivue/dist/niivue.umd.js "$vendor/niivue.umd.js"
sum="$(sha256sum "$vendor/niivue.umd.js" | cut -d' ' -f1)"
printf '@niivue/niivue %s\nfile dist/niivue.umd.js of the npm package\nsha256 %s\nlicense BSD-2-Clause (LICENSES.txt)\n' \
    "$VERSION" "$sum" > "$vendor/VERSION"
{
    echo "The file niivue.umd.js is NiiVue $VERSION (https://github.com/niivue/niivue), built by its authors"
    echo "and published on npm as @niivue/niivue. Its licence, and those of the packages bundled into it, follow."
    echo
    echo "=== @niivue/niivue $VERSION: BSD-2-Clause (the npm package carries no LICENSE file; this is the"
    echo "=== text of https://github.com/niivue/niivue/blob/main/LICENSE)"
    cat <<'BSD'
BSD 2-Clause License

Copyright (c) 2021, Niivue
All rights reserved.

Redistribution and use in source and binary forms, with or without
modification, are permitted provided that the following conditions are met:

1. Redistributions of source code must retain the above copyright notice, this
   list of conditions and the following disclaimer.

2. Redistributions in binary form must reproduce the above copyright notice,
   this list of conditions and the following disclaimer in the documentation
   and/or other materials provided with the distribution.

THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS"
AND ANY EXPRESS OR IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE
IMPLIED WARRANTIES OF MERCHANTABILITY AND FITNESS FOR A PARTICULAR PURPOSE ARE
DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT HOLDER OR CONTRIBUTORS BE LIABLE
FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL, EXEMPLARY, OR CONSEQUENTIAL
DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR
SERVICES; LOSS OF USE, DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER
CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY,
OR TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE
OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.
BSD
    # the runtime dependencies the bundle includes, at the ranges NiiVue asks for
    node -e 'const d=require("./niivue/package.json").dependencies; for (const [k,v] of Object.entries(d)) console.log(k+"@"+v)' |
    while read -r spec; do
        name="${spec%@*}"
        mkdir -p dep && rm -rf dep/*
        tarball="$(npm pack --silent "$spec")"
        tar xzf "$tarball" -C dep --strip-components=1
        version="$(node -e 'console.log(require("./dep/package.json").version)')"
        license="$(node -e 'const p=require("./dep/package.json"); console.log(p.license||"")')"
        echo
        echo "=== $name $version: $license"
        found="$(find dep -maxdepth 1 -iname 'licen[sc]e*' | head -1)"
        if [ -n "$found" ]; then cat "$found"; else echo "(no licence file in the npm package; licence field: $license)"; fi
        rm -f "$tarball"
    done
} > "$vendor/LICENSES.txt"
echo "vendored @niivue/niivue $VERSION ($sum) into $vendor"
