"""The core layer: geometry, kinematics, errors, clock, YAML loading, the plan/cell/object
specs, device protocols, safety and the force loop. It imports nothing above it
(docs/design.md, "Layers")."""
