// Chunked, resumable upload for the submit page (the same API the CLI uses).
"use strict";
(function () {
  const CHUNK = 16 * 1024 * 1024;
  const form = document.getElementById("submit-form");
  if (!form) return;
  const csrf = document.querySelector('meta[name="csrf-token"]').content;
  const statusBox = document.getElementById("upload-status");
  const bar = document.getElementById("upload-progress");
  const text = document.getElementById("upload-text");
  const errorBox = document.getElementById("upload-error");
  const button = document.getElementById("submit-button");

  async function api(method, url, body, isJson) {
    const headers = { "X-CSRF-Token": csrf };
    if (isJson) headers["Content-Type"] = "application/json";
    const response = await fetch(url, {
      method, headers, body: isJson ? JSON.stringify(body) : body, credentials: "same-origin",
    });
    let data = null;
    try { data = await response.json(); } catch (e) { data = null; }
    if (!response.ok) {
      const error = new Error((data && data.error) || ("HTTP " + response.status));
      error.problems = (data && data.problems) || [];
      error.offset = data && data.offset;
      error.status = response.status;
      throw error;
    }
    return data;
  }

  function showError(error) {
    errorBox.hidden = false;
    errorBox.textContent = "";
    const head = document.createElement("p");
    head.textContent = error.message;
    errorBox.appendChild(head);
    if (error.problems && error.problems.length) {
      const list = document.createElement("ul");
      list.id = "problems";
      for (const problem of error.problems) {
        const item = document.createElement("li");
        item.textContent = problem;
        list.appendChild(item);
      }
      errorBox.appendChild(list);
    }
  }

  function show(done, total) {
    bar.max = total;
    bar.value = done;
    text.textContent = (100 * done / total).toFixed(1) + " % of " + total.toLocaleString() + " bytes";
  }

  async function sendChunks(upload, file) {
    let offset = upload.received_bytes;
    let failures = 0;
    while (offset < file.size) {
      const end = Math.min(offset + CHUNK, file.size);
      try {
        const answer = await api("PUT", "/api/uploads/" + upload.id + "?offset=" + offset,
                                 file.slice(offset, end), false);
        offset = answer.received_bytes;
        failures = 0;
      } catch (error) {
        if (error.status && error.status < 500 && error.status !== 409) throw error;
        if (++failures > 5) throw error;
        await new Promise((resolve) => setTimeout(resolve, 1000 * failures));
        offset = (await api("GET", "/api/uploads/" + upload.id)).received_bytes;
      }
      show(offset, file.size);
    }
  }

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    errorBox.hidden = true;
    const data = new FormData(form);
    const file = data.get("file");
    if (!file || !file.size) { showError(new Error("choose a non-empty zip file")); return; }
    button.disabled = true;
    statusBox.hidden = false;
    try {
      const upload = await api("POST", "/api/uploads", {
        challenge: data.get("challenge"), size_bytes: file.size, filename: file.name,
      }, true);
      show(upload.received_bytes, file.size);
      await sendChunks(upload, file);
      text.textContent = "validating…";
      const runtime = data.get("runtime_s");
      const submission = await api("POST", "/api/uploads/" + upload.id + "/finalize", {
        method: {
          name: data.get("name"), description: data.get("description") || "",
          paper_url: data.get("paper_url") || "", code_url: data.get("code_url") || "",
          runtime_s: runtime ? Number(runtime) : null, hardware: data.get("hardware") || null,
        },
      }, true);
      window.location.assign("/submissions/" + submission.id);
    } catch (error) {
      statusBox.hidden = true;
      showError(error);
      button.disabled = false;
    }
  });
})();
