"""HTTP routes: OGC API – Processes core, jobs and outputs, surveys."""
