export function renderVehicle(main, id) {
  main.innerHTML = `<section class="page"><h1>${id}</h1></section>`;
  return () => {};
}
