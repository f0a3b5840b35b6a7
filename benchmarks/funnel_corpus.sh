#!/bin/bash
# The cascade funnel on the Waymo sample and one scene of each recorded dataset.
# Usage: benchmarks/funnel_corpus.sh OUT_DIR [MAP_PATH_M]
#   converts the scenes into OUT_DIR (map paths followed MAP_PATH_M metres, default 300;
#   0 gives paths of v*T + margin only) and prints each scene's funnel from `replay run`.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
DATA=${RISKREPLAY_SHARED_DATA:-$ROOT/../shared/data}
D=$DATA/recorded
O=$1
M=${2:-300}
mkdir -p "$O"
R="$ROOT/.venv/bin/replay"
C=(--map-path-m "$M")
$R convert waymo "$DATA/waymo/womd_637f20cafde22ff8.tfrecord" -o "$O/waymo.mcap" "${C[@]}" >/dev/null 2>&1
$R convert interaction "$D/interaction/vehicle_tracks_000.csv" "$D/interaction/pedestrian_tracks_000.csv" -o "$O/interaction.mcap" "${C[@]}" >/dev/null 2>&1
$R convert av2-sensor "$D/av2-sensor/adcf7d18-0510-35b0-a2fa-b4cea13a6d76" -o "$O/av2s.mcap" "${C[@]}" >/dev/null 2>&1
$R convert commonroad "$D/sind/CHN_SIND-851_1_T-75.cr.xml" -o "$O/sind.mcap" "${C[@]}" >/dev/null 2>&1
$R convert commonroad "$D/highd/DEU_LocationAUpper26-1_26150_T-225.cr.xml" -o "$O/highd.mcap" "${C[@]}" >/dev/null 2>&1
$R convert commonroad "$D/exid/DEU_AachenBrand-1_431880_T-1955.cr.xml" -o "$O/exid.mcap" "${C[@]}" >/dev/null 2>&1
$R convert commonroad "$D/ind/DEU_AachenBendplatz-1_90_T-300.xml" -o "$O/ind.mcap" "${C[@]}" >/dev/null 2>&1
$R convert commonroad "$D/mona/C-DEU_MONAEast-2_1600_T-1679.xml" -o "$O/mona.mcap" "${C[@]}" >/dev/null 2>&1
$R convert commonroad "$(ls "$D"/ngsim/*.xml | head -1)" -o "$O/ngsim.mcap" "${C[@]}" >/dev/null 2>&1
for s in waymo interaction av2s sind highd exid ind mona ngsim; do
  echo "== $s"
  $R run "$O/$s.mcap" --no-rrd --no-progress 2>&1 | grep -E "frames,|all other|path_distance|trajectory_distance|gaussian  "
done
