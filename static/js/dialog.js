// One confirmation dialog for every command: native <dialog>, so focus and Escape just work.

const dialog = document.getElementById("confirm");

/**
 * Ask before sending; resolves true when the user confirms. `reach` ({text, units: [label]})
 * lists the units a write reaches.
 */
export function confirmAction(title, text, okLabel = "Send", reach = null) {
  dialog.querySelector("#confirm-title").textContent = title;
  dialog.querySelector("#confirm-text").textContent = text;
  const box = dialog.querySelector("#confirm-reach");
  box.hidden = !reach;
  dialog.querySelector("#confirm-reach-text").textContent = reach?.text || "";
  const list = dialog.querySelector("#confirm-units");
  list.replaceChildren(
    ...(reach?.units || []).map((u) => {
      const li = document.createElement("li");
      li.textContent = u.label;
      li.dataset.sa = u.sa;
      return li;
    }),
  );
  dialog.querySelector("#confirm-ok").textContent = okLabel;
  dialog.returnValue = "cancel";
  dialog.showModal();
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "ok"), { once: true });
  });
}
