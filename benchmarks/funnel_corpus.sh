#!/bin/bash
# usage: funnel.sh OUTDIR  -- converts a fixed set of corpus scenes and prints each cascade funnel
cd /work/wt/sources
D=/work/shared/data/recorded
O=$1; mkdir -p $O
R=.venv/bin/replay
$R convert waymo /work/shared/data/waymo/womd_637f20cafde22ff8.tfrecord -o $O/waymo.mcap 2>/dev/null >/dev/null
$R convert interaction $D/interaction/vehicle_tracks_000.csv $D/interaction/pedestrian_tracks_000.csv -o $O/interaction.mcap 2>/dev/null >/dev/null
$R convert av2-sensor $D/av2-sensor/adcf7d18-0510-35b0-a2fa-b4cea13a6d76 -o $O/av2s.mcap 2>/dev/null >/dev/null
$R convert commonroad $D/sind/CHN_SIND-851_1_T-75.cr.xml -o $O/sind.mcap 2>/dev/null >/dev/null
$R convert commonroad $D/highd/DEU_LocationAUpper26-1_26150_T-225.cr.xml -o $O/highd.mcap 2>/dev/null >/dev/null
$R convert commonroad $D/exid/DEU_AachenBrand-1_431880_T-1955.cr.xml -o $O/exid.mcap 2>/dev/null >/dev/null
$R convert commonroad $D/ind/DEU_AachenBendplatz-1_90_T-300.xml -o $O/ind.mcap 2>/dev/null >/dev/null
$R convert commonroad $D/mona/C-DEU_MONAEast-2_1600_T-1679.xml -o $O/mona.mcap 2>/dev/null >/dev/null
$R convert commonroad $(ls $D/ngsim/*.xml | head -1) -o $O/ngsim.mcap 2>/dev/null >/dev/null
for s in waymo interaction av2s sind highd exid ind mona ngsim; do
  echo "== $s"; $R run $O/$s.mcap --no-rrd --no-progress 2>&1 | grep -E "frames,|all other|path_distance|trajectory_distance|gaussian  "
done
