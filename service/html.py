"""HTML representations of the OGC API - Processes resources, for a browser: the landing page,
the conformance declaration, the process list, a process, the job list and a job.

JSON stays the default; HTML is answered for ``?f=html`` or when the ``Accept`` header prefers
``text/html`` (as a browser's does). The pages are rendered on the server from the very JSON
documents the API answers; every value is escaped, and only links to this API or to http(s)
addresses become anchors.
"""

from __future__ import annotations

import json
from html import escape
from typing import Any

from fastapi import Request
from fastapi.responses import HTMLResponse

from service.problems import Problem

HEADERS = {
    "Content-Security-Policy": "default-src 'none'; style-src 'self'; img-src 'self'; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Vary": "Accept",
}
FORMATS = ("json", "html")


def _quality(accept: str) -> dict[str, tuple[float, int]]:
    """Each media range of an Accept header: its q value and its position."""
    ranges: dict[str, tuple[float, int]] = {}
    for position, item in enumerate(accept.split(",")):
        media, *params = (p.strip() for p in item.split(";"))
        q = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        if media:
            ranges.setdefault(media.lower(), (q, position))
    return ranges


def wants_html(request: Request) -> bool:
    """``?f=html`` or ``?f=json`` decide; else HTML when the Accept header names text/html with
    a higher preference than application/json (``*/*`` alone means JSON)."""
    f = request.query_params.get("f")
    if f is not None:
        if f.lower() not in FORMATS:
            raise Problem(400, "invalid-parameter", f"f: {f!r} is not one of json, html",
                          errors=[{"parameter": "f", "message": "use json or html"}])
        return f.lower() == "html"
    ranges = _quality(request.headers.get("accept", ""))
    html = max((ranges.get(m, (0.0, 99)) for m in ("text/html", "application/xhtml+xml")),
               key=lambda r: r[0])
    as_json = ranges.get("application/json", (0.0, 99))
    return html[0] > 0 and (html[0], -html[1]) > (as_json[0], -as_json[1])


def _href(href: Any) -> str | None:
    text = str(href)
    return text if text.startswith(("/", "http://", "https://")) else None


def link(href: Any, text: Any) -> str:
    target = _href(href)
    if target is None:
        return escape(str(text))
    return f'<a href="{escape(target, quote=True)}">{escape(str(text))}</a>'


def value(node: Any) -> str:
    """Any JSON value as nested definition lists and lists, escaped."""
    if isinstance(node, dict):
        if not node:
            return "<i>none</i>"
        items = "".join(f"<dt>{escape(str(k))}</dt><dd>{value(v)}</dd>" for k, v in node.items())
        return f"<dl>{items}</dl>"
    if isinstance(node, list):
        return "<ul>" + "".join(f"<li>{value(v)}</li>" for v in node) + "</ul>"
    if node is None:
        return "<i>null</i>"
    return escape(node if isinstance(node, str) else json.dumps(node))


def links_list(links: list[dict[str, Any]]) -> str:
    items = "".join(
        f"<li>{link(item.get('href', ''), item.get('title') or item.get('href', ''))} "
        f"<small>({escape(str(item.get('rel', '')))}"
        f"{', ' + escape(str(item['type'])) if item.get('type') else ''})</small></li>"
        for item in links)
    return f"<h2>Links</h2><ul>{items}</ul>" if items else ""


def table(headers: list[str], rows: list[list[str]]) -> str:
    """A table of already escaped cells."""
    head = "".join(f"<th>{escape(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def page(title: str, body: str, json_href: str) -> HTMLResponse:
    document = (
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{escape(title)} - lidar-outliers</title>"
        '<link rel="stylesheet" href="/app/static/app.css"></head><body>'
        f'<nav>{link("/", "lidar-outliers")} · {link("/processes?f=html", "processes")} · '
        f'{link("/jobs?f=html", "jobs")} · {link("/conformance?f=html", "conformance")} · '
        f'{link(json_href, "this page as JSON")}</nav>'
        f"<h1>{escape(title)}</h1>{body}</body></html>")
    return HTMLResponse(document, headers=HEADERS)


def _with_f(path: str, f: str = "json") -> str:
    return f"{path}{'&' if '?' in path else '?'}f={f}"


def landing(doc: dict[str, Any]) -> HTMLResponse:
    body = f"<p>{escape(doc.get('description', ''))}</p>{links_list(doc.get('links', []))}"
    return page(doc.get("title", "lidar-outliers"), body, "/?f=json")


def conformance(doc: dict[str, Any]) -> HTMLResponse:
    items = "".join(f"<li>{link(uri, uri)}</li>" for uri in doc.get("conformsTo", []))
    return page("Conformance", f"<ul>{items}</ul>", "/conformance?f=json")


def processes(doc: dict[str, Any]) -> HTMLResponse:
    rows = [[link(f"/processes/{p['id']}?f=html", p["id"]), escape(p.get("title", "")),
             escape(p.get("description", "")), escape(", ".join(p.get("jobControlOptions", [])))]
            for p in doc.get("processes", [])]
    body = table(["id", "title", "description", "job control"], rows)
    return page("Processes", body, "/processes?f=json")


def process(doc: dict[str, Any]) -> HTMLResponse:
    inputs = [[escape(name), escape(i.get("title", "")), escape(i.get("description", "")),
               escape(str(i.get("minOccurs", 1))), value(i.get("schema", {}))]
              for name, i in doc.get("inputs", {}).items()]
    outputs = [[escape(name), escape(o.get("title", "")), escape(o.get("description", "")),
                value(o.get("schema", {}))] for name, o in doc.get("outputs", {}).items()]
    body = (f"<p>{escape(doc.get('description', ''))}</p>"
            f"<p>Version {escape(doc.get('version', ''))}; job control: "
            f"{escape(', '.join(doc.get('jobControlOptions', [])))}; outputs by "
            f"{escape(', '.join(doc.get('outputTransmission', [])))}.</p>"
            "<h2>Inputs</h2>" + table(["name", "title", "description", "minOccurs", "schema"],
                                      inputs)
            + "<h2>Outputs</h2>" + table(["name", "title", "description", "schema"], outputs)
            + links_list(doc.get("links", [])))
    return page(doc.get("title", doc.get("id", "process")), body,
                f"/processes/{doc.get('id', '')}?f=json")


def jobs(doc: dict[str, Any], self_href: str) -> HTMLResponse:
    rows = [[link(f"/jobs/{j['jobID']}?f=html", j["jobID"]), escape(j.get("processID", "")),
             escape(j.get("status", "")), escape(str(j.get("progress", ""))),
             escape(j.get("created", "")), escape(j.get("finished", "")),
             escape(j.get("message", ""))] for j in doc.get("jobs", [])]
    body = (f"<p>{doc.get('numberReturned', 0)} of {doc.get('numberMatched', 0)} jobs.</p>"
            + table(["job", "process", "status", "progress %", "created", "finished",
                     "message"], rows)
            + links_list(doc.get("links", [])))
    return page("Jobs", body, _with_f(self_href))


def job(doc: dict[str, Any]) -> HTMLResponse:
    fields = {k: v for k, v in doc.items() if k != "links"}
    body = value(fields) + links_list(doc.get("links", []))
    return page(f"Job {doc.get('jobID', '')}", body, f"/jobs/{doc.get('jobID', '')}?f=json")
