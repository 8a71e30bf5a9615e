"""Sources: where single-pixel measurements come from (simulator, recorded file, device)."""
