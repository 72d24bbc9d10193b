"""The paper's studies as functions: FCC plane strain, time-step study, stability threshold."""
