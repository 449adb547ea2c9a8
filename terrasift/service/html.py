"""HTML for people: content negotiation and the pages' markup.

A request wants HTML when it says ``f=html``, or when its ``Accept`` header
ranks ``text/html`` above JSON (browsers do; curl's and most clients' ``*/*``
does not), unless it says ``f=json``. Pages are server-rendered strings with a
little plain JavaScript on the job page; nothing is fetched from elsewhere.
"""

from __future__ import annotations

from html import escape
from typing import Any
from urllib.parse import parse_qs

from starlette.types import Scope

from terrasift.tiling import quicklook as ql


def _q(params: str) -> float:
    for p in params.split(";"):
        key, _, value = p.strip().partition("=")
        if key == "q":
            try:
                return float(value)
            except ValueError:
                return 0.0
    return 1.0


def wants_html(scope: Scope) -> bool:
    """True for ``f=html``, or an ``Accept`` that prefers ``text/html`` to JSON."""
    query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
    f = (query.get("f") or [""])[0].lower()
    if f in ("html", "json"):
        return f == "html"
    accept = ""
    for key, value in scope.get("headers", []):
        if key == b"accept":
            accept = value.decode("latin-1")
    q_html = q_json = 0.0
    for item in accept.split(","):
        media, _, params = item.strip().partition(";")
        media, q = media.strip().lower(), _q(params)
        if media in ("text/html", "application/xhtml+xml"):
            q_html = max(q_html, q)
        elif media in ("application/json", "application/*", "*/*") or media.endswith("+json"):
            q_json = max(q_json, q)
    return q_html > q_json


STYLE = """
body{font:15px/1.45 system-ui,sans-serif;margin:0;color:#1d2327;background:#f6f7f7}
header{background:#1f3b2c;color:#fff;padding:.6em 1.2em;display:flex;gap:1.2em;align-items:baseline}
header a{color:#d8efe0;text-decoration:none}header strong a{color:#fff;font-size:1.2em}
main{max-width:1100px;margin:1em auto;padding:0 1.2em}
h1{font-size:1.5em;margin:.4em 0}h2{font-size:1.15em;margin:1.4em 0 .5em}
table{border-collapse:collapse;width:100%;background:#fff}
td,th{border-bottom:1px solid #e2e4e7;padding:.35em .6em;text-align:left;vertical-align:top}
th{background:#eef0f1}code{background:#eef0f1;padding:0 .25em;border-radius:3px}
.bar{background:#dde3e0;border-radius:4px;height:1.3em;overflow:hidden;width:100%}
.bar>div{background:#2f7d4f;height:100%;transition:width .4s}
.status{display:inline-block;padding:.1em .6em;border-radius:1em;color:#fff;background:#6b7780}
.status.running{background:#1d6fa5}.status.successful{background:#2f7d4f}
.status.failed{background:#b3261e}.status.dismissed{background:#6b7780}.status.accepted{background:#8a6d00}
.warnings li{color:#8a4b00}.muted{color:#5f6b73}
.looks{display:grid;grid-template-columns:repeat(auto-fill,minmax(300px,1fr));gap:1em}
.looks figure{margin:0;background:#fff;padding:.5em;border:1px solid #e2e4e7}
.looks img{width:100%;image-rendering:pixelated;background:repeating-conic-gradient(#eee 0 25%,#fff 0 50%) 0 0/16px 16px}
.legend{list-style:none;padding:0;margin:.3em 0 0;font-size:.85em;display:flex;flex-wrap:wrap;gap:.2em .8em}
.legend span{display:inline-block;width:.9em;height:.9em;border:1px solid #999;vertical-align:-.1em;margin-right:.3em}
form.upload{background:#fff;border:1px solid #e2e4e7;padding:1em}
form.upload textarea{width:100%;font-family:monospace}
button{background:#2f7d4f;color:#fff;border:0;padding:.45em 1em;border-radius:4px;cursor:pointer}
button.danger{background:#b3261e}
"""


def page(title: str, body: str, json_href: str, base: str = "/") -> str:
    """A whole HTML document with the site header and a link to the JSON of the same resource.

    Links are relative to ``base`` (the service's base URL), so pages work behind
    a proxy that serves the API under a path prefix."""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><base href="{escape(base)}">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{escape(title)} · terrasift</title>
<link rel="alternate" type="application/json" href="{escape(json_href)}">
<style>{STYLE}</style></head>
<body><header><strong><a href="./?f=html">terrasift</a></strong>
<a href="processes?f=html">processes</a><a href="jobs?f=html">jobs</a>
<a href="docs">API docs</a><a href="{escape(json_href)}">JSON</a></header>
<main>{body}</main></body></html>"""


def upload_form() -> str:
    return """<form class="upload" action="jobs" method="post" enctype="multipart/form-data">
<p><label>LAS/LAZ tiles <input type="file" name="file" id="file" multiple required
 accept=".las,.laz"></label></p>
<p><label>Parameters (JSON, optional)<br><textarea name="params" id="params" rows="2"
 placeholder='{"resolution": 1.0}'></textarea></label></p>
<button type="submit" id="submit">Start a job</button></form>"""


def size(n: int) -> str:
    x = float(n)
    for unit in ("B", "kB", "MB", "GB"):
        if x < 1000 or unit == "GB":
            return f"{x:.0f} {unit}" if unit == "B" else f"{x:.1f} {unit}"
        x /= 1000
    return f"{x} B"


def links_list(links: list[dict[str, Any]]) -> str:
    items = "".join(
        f'<li><a href="{escape(ln["href"])}">{escape(ln.get("title") or ln["rel"])}</a> '
        f'<span class="muted">{escape(ln["rel"])}</span></li>'
        for ln in links
    )
    return f"<ul>{items}</ul>"


def landing_page(doc: dict[str, Any], jobs_table: str) -> str:
    body = (
        f"<h1>{escape(doc['title'])}</h1><p>{escape(doc['description'])}</p>"
        f"<h2>Process tiles</h2>{upload_form()}"
        f"<h2>Recent jobs</h2>{jobs_table}<h2>Links</h2>{links_list(doc['links'])}"
    )
    return page("terrasift", body, "./?f=json")


def processes_page(doc: dict[str, Any]) -> str:
    rows = "".join(
        f'<tr><td><a href="processes/{escape(p["id"])}?f=html">{escape(p["id"])}</a></td>'
        f"<td>{escape(p['title'])}</td><td>{escape(p['description'])}</td></tr>"
        for p in doc["processes"]
    )
    body = f"<h1>Processes</h1><table><tr><th>id</th><th>title</th><th>what</th></tr>{rows}</table>"
    return page("Processes", body, "processes?f=json")


def process_page(doc: dict[str, Any]) -> str:
    def row(key: str, spec: dict[str, Any]) -> str:
        schema = spec.get("schema", {})
        kind = schema.get("type") or ", ".join(
            str(s.get("type") or s.get("$ref", "")) for s in schema.get("anyOf", [])
        )
        default = schema.get("default")
        return (
            f"<tr><td><code>{escape(key)}</code></td><td>{escape(str(kind or ''))}</td>"
            f"<td>{'' if default is None else escape(str(default))}</td>"
            f"<td>{escape(spec.get('description', ''))}</td></tr>"
        )

    inputs = "".join(row(k, v) for k, v in doc["inputs"].items())
    outputs = "".join(
        f"<tr><td><code>{escape(k)}</code></td><td>{escape(v['schema'].get('contentMediaType', ''))}</td>"
        f"<td>{escape(v.get('description', ''))}</td></tr>"
        for k, v in doc["outputs"].items()
    )
    body = (
        f"<h1>{escape(doc['title'])} <span class='muted'>({escape(doc['id'])} "
        f"{escape(doc['version'])})</span></h1><p>{escape(doc['description'])}</p>"
        f"<p>Execution: {escape(', '.join(doc['jobControlOptions']))}. "
        f"<code>POST /processes/{escape(doc['id'])}/execution</code>, or upload below.</p>"
        f"{upload_form()}<h2>Inputs</h2><table><tr><th>id</th><th>type</th><th>default</th>"
        f"<th>meaning</th></tr>{inputs}</table><h2>Outputs</h2><table><tr><th>id</th>"
        f"<th>media type</th><th>what</th></tr>{outputs}</table>"
    )
    return page(doc["title"], body, f"processes/{doc['id']}?f=json")


def jobs_table(jobs: list[dict[str, Any]]) -> str:
    if not jobs:
        return "<p class='muted'>No jobs yet.</p>"
    rows = "".join(
        f'<tr><td><a href="jobs/{escape(j["jobID"])}?f=html">{escape(j["jobID"][:12])}</a></td>'
        f'<td><span class="status {escape(j["status"])}">{escape(j["status"])}</span></td>'
        f"<td>{j.get('progress', 0)} %</td><td>{escape(j.get('message', ''))}</td>"
        f"<td>{escape((j.get('created') or '')[:19].replace('T', ' '))}</td></tr>"
        for j in jobs
    )
    return (
        "<table><tr><th>job</th><th>status</th><th>progress</th><th>message</th>"
        f"<th>created (UTC)</th></tr>{rows}</table>"
    )


def jobs_page(doc: dict[str, Any]) -> str:
    nxt = [ln for ln in doc["links"] if ln["rel"] == "next"]
    more = f'<p><a href="{escape(nxt[0]["href"])}&f=html">older jobs</a></p>' if nxt else ""
    body = f"<h1>Jobs</h1>{jobs_table(doc['jobs'])}{more}<h2>New job</h2>{upload_form()}"
    return page("Jobs", body, "jobs?f=json")


LEGENDS = {
    "coverage.png": ql.COVERAGE_CLASSES,
    "categories.png": {
        **ql.INCLINATION_CLASSES,
        **{10 + k: v for k, v in ql.STATE_CLASSES.items()},
    },
    "features.png": {i: (kind, rgb) for i, (kind, rgb) in enumerate(ql.FEATURE_COLOURS.items())},
    "steep_blocks.png": {0: ("rotated classification", (220, 30, 30))},
}
CAPTIONS = {
    "hillshade.png": "DTM hillshade",
    "chm.png": "canopy height (light: low, dark green: high)",
    "coverage.png": "vegetation coverage",
    "categories.png": "terrain categories",
    "features.png": "terrain objects over the hillshade",
    "steep_blocks.png": "steep blocks over the hillshade",
}


def legend_html(name: str) -> str:
    classes = LEGENDS.get(name)
    if not classes:
        return ""
    items = "".join(
        f'<li><span style="background:#{"".join(f"{c:02x}" for c in rgb)}"></span>{escape(label)}</li>'
        for label, rgb in classes.values()
    )
    return f'<ul class="legend">{items}</ul>'


def job_page(status: dict[str, Any], outputs: list[tuple[str, int, str]], output_href: str) -> str:
    """The job: live status and progress (server-sent events, polling as a fallback),
    warnings, queue position, outputs with sizes, quicklooks."""
    job_id = status["jobID"]
    warnings = "".join(f"<li>{escape(w)}</li>" for w in status.get("warnings", []))
    queue = status.get("queuePosition")
    rows = "".join(
        f'<tr><td><a href="{escape(output_href)}/{escape(n)}" download>{escape(n)}</a></td>'
        f"<td>{size(b)}</td><td class='muted'>{escape(t)}</td></tr>"
        for n, b, t in outputs
    )
    looks = "".join(
        f'<figure><a href="{escape(output_href)}/{escape(n)}"><img src="{escape(output_href)}/'
        f'{escape(n)}" alt="{escape(CAPTIONS[n])}" id="look-{escape(n[:-4])}"></a>'
        f"<figcaption>{escape(CAPTIONS[n])}{legend_html(n)}</figcaption></figure>"
        for n in CAPTIONS
        if n in {o[0] for o in outputs}
    )
    final = status["status"] not in ("accepted", "running")
    body = f"""<h1>Job <code>{escape(job_id)}</code></h1>
<p><span class="status {escape(status["status"])}" id="status">{escape(status["status"])}</span>
 <span id="queue" class="muted">{"" if queue is None else f"position {queue} in the queue"}</span></p>
<div class="bar"><div id="bar" style="width:{int(status.get("progress", 0))}%"></div></div>
<p><strong id="progress">{int(status.get("progress", 0))} %</strong> · <span id="message">{escape(status.get("message", ""))}</span></p>
<p class="muted">created {escape(status.get("created", ""))}
{" · started " + escape(status["started"]) if status.get("started") else ""}
{" · finished " + escape(status["finished"]) if status.get("finished") else ""}</p>
<h2>Warnings</h2><ul class="warnings" id="warnings">{warnings or "<li class='muted'>none</li>"}</ul>
{"" if final else '<p><button class="danger" id="dismiss">Dismiss job</button></p>'}
{f"<h2>Quicklooks</h2><div class='looks'>{looks}</div>" if looks else ""}
<h2>Outputs</h2>{f"<table id='outputs'><tr><th>file</th><th>size</th><th>type</th></tr>{rows}</table>" if rows else "<p class='muted' id='outputs'>Outputs appear when the job is successful.</p>"}
<script>
(function () {{
  const url = "jobs/{escape(job_id)}";
  const initial = "{escape(status["status"])}";
  const active = s => s === "accepted" || s === "running";
  function text(id, value) {{ const el = document.getElementById(id); if (el) el.textContent = value; }}
  function show(s) {{
    const st = document.getElementById("status");
    st.textContent = s.status; st.className = "status " + s.status;
    document.getElementById("bar").style.width = (s.progress || 0) + "%";
    text("progress", (s.progress || 0) + " %");
    text("message", s.message || "");
    text("queue", s.queuePosition === undefined ? "" : "position " + s.queuePosition + " in the queue");
    const w = document.getElementById("warnings");
    if (s.warnings && s.warnings.length) {{
      w.replaceChildren(...s.warnings.map(m => {{ const li = document.createElement("li"); li.textContent = m; return li; }}));
    }}
    if (!active(s.status) && active(initial)) setTimeout(() => location.reload(), 300);
    return active(s.status);
  }}
  function poll() {{
    fetch(url + "?f=json", {{headers: {{Accept: "application/json"}}}})
      .then(r => r.json()).then(s => {{
        document.body.dataset.live = "polling";
        if (show(s)) setTimeout(poll, 1000);
      }})
      .catch(() => setTimeout(poll, 3000));
  }}
  if (active(initial)) {{
    if (window.EventSource) {{
      const es = new EventSource(url + "/events");
      es.addEventListener("status", e => {{
        document.body.dataset.live = "events";
        if (!show(JSON.parse(e.data))) es.close();
      }});
      es.onerror = () => {{ es.close(); poll(); }};
    }} else {{ poll(); }}
  }}
  const d = document.getElementById("dismiss");
  if (d) d.onclick = () => fetch(url, {{method: "DELETE"}}).then(() => location.reload());
}})();
</script>"""
    return page(f"Job {job_id[:12]}", body, f"jobs/{job_id}?f=json")


def conformance_page(doc: dict[str, Any]) -> str:
    items = "".join(f"<li><code>{escape(c)}</code></li>" for c in doc["conformsTo"])
    return page(
        "Conformance", f"<h1>Conformance classes</h1><ul>{items}</ul>", "conformance?f=json"
    )


def results_page(job_id: str, doc: dict[str, Any]) -> str:
    rows = "".join(
        f'<tr><td><a href="{escape(v["href"])}">{escape(k)}</a></td><td>{escape(v["type"])}</td></tr>'
        for k, v in doc.items()
    )
    body = (
        f'<h1>Results of job <a href="jobs/{escape(job_id)}?f=html"><code>{escape(job_id)}</code></a></h1>'
        f"<table><tr><th>output</th><th>type</th></tr>{rows}</table>"
    )
    return page("Results", body, f"jobs/{job_id}/results?f=json")


def problem_page(status: int, title: str, detail: str) -> str:
    body = (
        f"<h1>{status} · {escape(title)}</h1><p>{escape(detail)}</p>"
        '<p><a href="./?f=html">back to the start page</a></p>'
    )
    return page(title, body, "./?f=json")
