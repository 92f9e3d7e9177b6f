"""ABB Externally Guided Motion, joint mode: schema and messages (`protocol`), the PC side for one arm
(`client`), a simulated arm (`sim`) and a lossy, slow UDP link for rehearsals (`faults`)."""
