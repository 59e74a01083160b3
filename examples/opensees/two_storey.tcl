# The 2-storey frame of two_storey.py for OpenSees' Tcl interpreter: its first-storey damper is
# tested through rths_hil (run `rths-hil run examples/opensees/site.toml` first).
#
#   OpenSees two_storey.tcl
#
# SI units (m, N, kg, s). Ground motion: one acceleration per line (m/s²), step 0.01 s, e.g.
# the bridge's bundled El Centro record written by tests/helpers/opensees_site.py:write_accel.

wipe
model basic -ndm 1 -ndf 1

node 1 0.0
node 2 0.0
node 3 0.0
fix 1 1
mass 2 50.0e3
mass 3 50.0e3

# storey columns
uniaxialMaterial Elastic 10 4.0e6
uniaxialMaterial Elastic 11 3.0e6
element zeroLength 10 1 2 -mat 10 -dir 1
element zeroLength 11 2 3 -mat 11 -dir 1

# the damper: tested by rths_hil (basic system: actuator = u2 - u1, forces (-f, +f))
element genericClient 3 -node 1 2 -dof 1 -dof 1 -server 8090 127.0.0.1
# ... or both storeys' dampers tested, two channels (rths-hil run examples/opensees/site_two.toml;
# actuator 1 = u2 - u1, actuator 2 = u3 - u2), instead of the line above:
# element genericClient 3 -node 1 2 3 -dof 1 -dof 1 -dof 1 -server 8090 127.0.0.1
# (the storey-2 damper of two_storey.py --dampers 2 as numerical: Elastic 0.8e6, Viscous 1.5e3)
# ... or, all-numerical (the reference):
# uniaxialMaterial Elastic 1 1.19e6
# uniaxialMaterial Viscous 2 2.0e3 1.0
# element zeroLength 3 1 2 -mat 1 2 -dir 1 1

timeSeries Path 1 -dt 0.01 -filePath accel.txt
pattern UniformExcitation 1 1 -accel 1

# 2 % mass-proportional damping at the first mode (f1 = 0.908 Hz with the damper's stiffness)
rayleigh [expr 2.0 * 0.02 * 2.0 * 3.141592653589793 * 0.908] 0.0 0.0 0.0

constraints Plain
numberer Plain
system FullGeneral
test NormDispIncr 1.0e-12 20
algorithm Linear
integrator NewmarkExplicit 0.5
analysis Transient

recorder Node -file floors.out -time -node 2 3 -dof 1 disp
analyze 2560 [expr 1.0 / 256.0]
wipe
