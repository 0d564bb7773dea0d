"""From a design to a part a process can make: processes and their rules, quantizing to made hole
sizes, the hole layout, the solid mesh, STEP, and reading holes back from a mesh.
"""
