// Requests to the job service with the API key as a Bearer header (no cookies: the key lives in
// this tab's sessionStorage). Every error becomes a Problem carrying the RFC 9457 document the
// service answered, or one made up when no answer came.

const STORAGE_KEY = "lidar-outliers-key";

export const apiKey = {
  get: () => sessionStorage.getItem(STORAGE_KEY),
  set: (value) => sessionStorage.setItem(STORAGE_KEY, value),
  clear: () => sessionStorage.removeItem(STORAGE_KEY),
};

export class Problem extends Error {
  constructor(doc) {
    const head = doc.status ? `${doc.status} ${doc.title || "Error"}` : doc.title || "Error";
    super(doc.detail ? `${head}: ${doc.detail}` : head);
    this.doc = doc;
    this.status = doc.status ?? null;
  }
}

function problemFromText(status, statusText, text) {
  let doc = null;
  try {
    doc = JSON.parse(text);
  } catch {
    doc = null;
  }
  if (!doc || typeof doc !== "object" || !(doc.title || doc.detail)) {
    doc = { title: statusText || "Error", detail: (text || "").slice(0, 200) };
  }
  doc.status ??= status;
  return new Problem(doc);
}

function unreachable(error) {
  return new Problem({ title: "Service unreachable", detail: String(error?.message || error) });
}

function authHeaders(headers = {}) {
  const out = new Headers(headers);
  out.set("Authorization", `Bearer ${apiKey.get() || ""}`);
  return out;
}

export async function request(path, options = {}) {
  let response;
  try {
    response = await fetch(path, { ...options, headers: authHeaders(options.headers),
                                   cache: "no-store", credentials: "omit" });
  } catch (error) {
    throw unreachable(error);
  }
  if (!response.ok) {
    throw problemFromText(response.status, response.statusText, await response.text());
  }
  return response;
}

export async function getJSON(path, options) {
  return (await request(path, options)).json();
}

// Multipart POST /processes/{id}/execution through XMLHttpRequest, whose upload events give
// the progress that fetch does not. Resolves with the job's status document.
export function submitJob(process, file, inputs, onProgress) {
  return new Promise((resolve, reject) => {
    const form = new FormData();
    form.append("file", file, file.name);
    if (inputs) form.append("inputs", JSON.stringify(inputs));
    const xhr = new XMLHttpRequest();
    xhr.open("POST", `/processes/${encodeURIComponent(process)}/execution`);
    xhr.setRequestHeader("Authorization", `Bearer ${apiKey.get() || ""}`);
    xhr.upload.addEventListener("progress", (event) => {
      if (event.lengthComputable) onProgress(event.loaded, event.total);
    });
    xhr.addEventListener("load", () => {
      if (xhr.status === 201) {
        resolve(JSON.parse(xhr.responseText));
      } else {
        reject(problemFromText(xhr.status, xhr.statusText, xhr.responseText));
      }
    });
    xhr.addEventListener("error", () => reject(unreachable("the upload was interrupted")));
    xhr.send(form);
  });
}

// A result saved by the browser: fetched with the key (a plain link cannot send it), read in
// chunks for the progress, then handed to the browser's download as a blob.
export async function saveFile(path, fallbackName, onProgress) {
  const response = await request(path);
  const total = Number(response.headers.get("content-length")) || 0;
  const reader = response.body.getReader();
  const parts = [];
  let done = 0;
  for (;;) {
    const { value, done: finished } = await reader.read();
    if (finished) break;
    parts.push(value);
    done += value.length;
    onProgress(done, total);
  }
  const type = response.headers.get("content-type") || "application/octet-stream";
  const url = URL.createObjectURL(new Blob(parts, { type }));
  const link = document.createElement("a");
  link.href = url;
  link.download = fileName(response.headers.get("content-disposition")) || fallbackName;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}

function fileName(disposition) {
  const match = /filename\*?=(?:UTF-8'')?"?([^";]+)"?/i.exec(disposition || "");
  return match ? decodeURIComponent(match[1]) : null;
}
