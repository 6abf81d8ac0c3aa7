"""Mechanics: total-Lagrangian finite-strain solver, skin membrane, gravity, rigid plates
with frictional contact, and the mammography protocols."""
