"""Files every phase writes and reads: atomic writes and digests (`fileio`), tensor files (`tensor_files`, NaN/Inf in `finite`),
validated JSON (`schema`), the seed's on-disk layout (`layout`), per-output locks (`locks`) and the
content fingerprints that make an output's identity (`fingerprints`)."""
