// Chunked, resumable upload for the submit page (the same API the CLI uses).
//
// Resuming: the id of each upload started here is kept in localStorage under the file's
// challenge, name, size and modification time; choosing the same file again continues
// from the bytes the server has (GET /api/uploads/{id}). The page also lists the
// account's unfinished uploads (GET /api/uploads) with a button to delete each.
"use strict";
(function () {
  const CHUNK = 16 * 1024 * 1024;
  const KEY_PREFIX = "semantic3d.upload:";
  const form = document.getElementById("submit-form");
  if (!form) return;
  const csrf = document.querySelector('meta[name="csrf-token"]').content;
  const statusBox = document.getElementById("upload-status");
  const bar = document.getElementById("upload-progress");
  const text = document.getElementById("upload-text");
  const errorBox = document.getElementById("upload-error");
  const button = document.getElementById("submit-button");
  const openBox = document.getElementById("open-uploads");
  const openList = document.getElementById("open-uploads-list");

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

  function remember(key, id) {
    try { if (id) localStorage.setItem(key, id); else localStorage.removeItem(key); }
    catch (e) { /* storage disabled: no resuming, uploads still work */ }
  }

  function recalled(key) {
    try { return localStorage.getItem(key); } catch (e) { return null; }
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

  function mib(n) { return (n / (1024 * 1024)).toFixed(1) + " MiB"; }

  function show(done, total) {
    bar.max = total;
    bar.value = done;
    text.textContent = (100 * done / total).toFixed(1) + " % of " + total.toLocaleString() + " bytes";
  }

  async function listOpenUploads() {
    if (!openBox) return;
    let answer;
    try { answer = await api("GET", "/api/uploads"); } catch (e) { return; }
    openList.textContent = "";
    for (const upload of answer.uploads) {
      const item = document.createElement("li");
      item.dataset.upload = upload.id;
      item.textContent = upload.filename + " (" + upload.challenge + "): " +
        mib(upload.received_bytes) + " of " + mib(upload.size_bytes) + " received ";
      const remove = document.createElement("button");
      remove.type = "button";
      remove.className = "delete-upload";
      remove.textContent = "Delete";
      remove.addEventListener("click", async () => {
        remove.disabled = true;
        try {
          await api("DELETE", "/api/uploads/" + upload.id);
        } catch (error) {
          showError(error);
        }
        await listOpenUploads();
      });
      item.appendChild(remove);
      openList.appendChild(item);
    }
    openBox.hidden = answer.uploads.length === 0;
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
        const retry = !error.status || error.status >= 500 || error.status === 408 ||
          error.status === 409;
        if (!retry || error.status === 507) throw error;
        if (++failures > 5) throw error;
        await new Promise((resolve) => setTimeout(resolve, 1000 * failures));
        offset = (await api("GET", "/api/uploads/" + upload.id)).received_bytes;
      }
      show(offset, file.size);
    }
  }

  async function openOrResume(key, challenge, file) {
    const known = recalled(key);
    if (known) {
      try {
        const upload = await api("GET", "/api/uploads/" + known);
        if (upload.size_bytes === file.size && upload.challenge === challenge) return upload;
      } catch (error) {
        if (error.status !== 404) throw error;
      }
      remember(key, null);
    }
    const upload = await api("POST", "/api/uploads", {
      challenge: challenge, size_bytes: file.size, filename: file.name,
    }, true);
    remember(key, upload.id);
    return upload;
  }

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    errorBox.hidden = true;
    const data = new FormData(form);
    const file = data.get("file");
    if (!file || !file.size) { showError(new Error("choose a non-empty zip file")); return; }
    const challenge = data.get("challenge");
    const key = KEY_PREFIX + [challenge, file.name, file.size, file.lastModified].join("|");
    button.disabled = true;
    statusBox.hidden = false;
    let upload = null;
    try {
      upload = await openOrResume(key, challenge, file);
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
      remember(key, null);
      window.location.assign("/submissions/" + submission.id);
    } catch (error) {
      // An invalid submission is deleted by the server: the next try then starts afresh.
      if (upload) {
        try { await api("GET", "/api/uploads/" + upload.id); }
        catch (e) { if (e.status === 404) remember(key, null); }
      }
      statusBox.hidden = true;
      showError(error);
      button.disabled = false;
      await listOpenUploads();
    }
  });

  listOpenUploads();
})();
